"""Multi-view 3-D reconstruction from a texcoord set (DESIGN §5 "Reconstruction").

Every gt vertex i carries its material coordinate T_G[i]. Camera p sees the inferred mesh
with texture coordinates T_N^p; the pixel where p shows material T_G[i] is therefore the
projection of the inferred-surface point whose T_N^p equals T_G[i]. So, per camera:

1. *Locate* T_G[i] in the UV image of the inferred mesh: rasterize the mesh with
   positions T_N^p into a triangle-id buffer (`raster.rasterize_uv`; drawn twice, in both
   orders, so two overlapping layers of a UV fold-over both leave ids), take the candidate
   triangles of the texels around T_G[i] and solve the 2x2 barycentric system exactly.
   Every triangle that contains T_G[i] is a hypothesis (texcoords may fold over).
2. The same barycentric combination of the inferred positions X_N is a 3-D point; it
   counts only where camera p sees it (depth test against a raster of the inferred mesh);
   its projection is the observation.

Then, per gt vertex with ≥ 2 observing cameras: linear DLT (vectorised over vertices),
Gauss-Newton on the reprojection error, the hypothesis combination with the least ray
disagreement, rejection of observations and points with implausible reprojection error
or distance to the inferred surface. Vertices that are not triangulated get X_N plus a
harmonic extension of the triangulated displacement (`extrapolate.fill`).
"""

from __future__ import annotations

import itertools
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp

from .camera import Camera, Rig
from .errors import InputError
from .mesh import barycentric_2d, edges, edge_strain, vertex_strain_energy, weld_groups, welded_adjacency

# Barycentric slack for "contains": points on a shared edge belong to both triangles
# (the duplicate 3-D points are merged afterwards).
_INSIDE_EPS = 1e-7
# Two hypotheses of one (vertex, camera) closer than this (m) are the same point.
_SAME_POINT_M = 1e-8


@dataclass(frozen=True)
class ReconOptions:
    """Options of the reconstruction (the `mvtex triangulate` flags mirror them).

    Attributes:
        max_reprojection_px: an observation whose reprojection error exceeds this is dropped
            (while ≥ 3 remain); a point still above it is rejected ("reprojection").
        max_surface_distance_m: a point farther than this from the inferred surface is
            rejected ("surface_distance").
        smooth: Taubin-smooth the reconstructed displacement (for noisy inputs, e.g. TSNN).
        smooth_iterations: Taubin passes (each a +lambda and a -mu step).
        uv_resolution: texels per side of the UV lookup buffer.
        depth_tolerance: relative depth slack of the visibility test.
        require_assigned: drop hypotheses in triangles with an unassigned (extrapolated)
            corner, when the texcoord set says which are assigned.
        max_combinations: at most this many hypothesis combinations are tried per vertex.
        refine_iterations: Gauss-Newton steps after the DLT.
        error_scale_m: error heatmaps run from blue (0) to red (≥ this).
        strain_scale: strain pictures run from blue (-this, compression) to red (+this).
    """

    max_reprojection_px: float = 2.0
    max_surface_distance_m: float = 0.05
    smooth: bool = False
    smooth_iterations: int = 10
    uv_resolution: int = 1024
    depth_tolerance: float = 0.005
    require_assigned: bool = True
    max_combinations: int = 256
    refine_iterations: int = 5
    error_scale_m: float = 0.01
    strain_scale: float = 0.1


@dataclass(frozen=True)
class Reconstruction:
    """Result of `reconstruct` for one pose, on the gt mesh's n vertices.

    Attributes:
        points: (n,3) float64 reconstructed positions (triangulated, or X_N + filled displacement).
        inferred: (n,3) float64 the inferred positions X_N of the gt vertices.
        triangulated: (n,) bool, True where the point was triangulated from its own material
            coordinate (seam copies of a triangulated vertex are pooled but stay False).
        observations: camera name -> (n,2) float64 OpenCV pixels used for vertex i; NaN where
            camera did not contribute to vertex i.
        reprojection_error: (n,) float64 mean reprojection error (px) of `points` over the
            used observations; NaN where not triangulated.
        rejected: reason -> number of vertices not triangulated for it ("fewer_than_2_views",
            "reprojection", "surface_distance", "cheirality").
        stats: counts of the locate/visibility/hypothesis stages.
        unsmoothed: (n,3) float64 points before smoothing, or None when not smoothed.
    """

    points: np.ndarray
    inferred: np.ndarray
    triangulated: np.ndarray
    observations: dict[str, np.ndarray]
    reprojection_error: np.ndarray
    rejected: dict[str, int]
    stats: dict[str, Any] = field(default_factory=dict)
    unsmoothed: np.ndarray | None = None

    @property
    def num_views(self) -> np.ndarray:
        """(n,) int number of cameras used per vertex."""
        return np.sum([np.isfinite(o[:, 0]) for o in self.observations.values()], axis=0).astype(np.int64)

    @property
    def displacement(self) -> np.ndarray:
        """(n,3) float64 points - inferred."""
        return self.points - self.inferred


# -- step 1: locate material coordinates on the texture-corrected inferred mesh ----------------

def locate_uv(points: np.ndarray, faces: np.ndarray, texcoords: np.ndarray, resolution: int = 1024,
              radius: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every triangle of a UV mesh that contains each query point.

    The mesh is rasterized in UV space into triangle-id buffers, each orientation (CCW and
    flipped triangles) separately and in both drawing orders (the last drawn triangle wins
    a texel), so the three layers of a fold-over all leave ids; the ids of the (2*radius+1)² texels
    around a point are the candidates, and exact barycentrics (float64) decide. A point
    with candidates but no containing one (a sliver smaller than a texel) is retried
    with the triangles sharing a vertex with the candidates.

    Args:
        points: (k,2) query uv.
        faces: (m,3) int triangles.
        texcoords: (n,2) per-vertex uv of the mesh (may fold over).
        resolution: texels per side of the id buffer.
        radius: neighbourhood radius in texels.

    Returns:
        point_index (h,) int64, face_index (h,) int64, bary (h,3) float64: one row per
        (point, containing triangle) pair, sorted by point.
    """
    from .raster import GLContext, rasterize_uv

    ctx = GLContext()
    points = np.asarray(points, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    texcoords = np.asarray(texcoords, dtype=np.float64)
    m = len(faces)
    R = int(resolution)
    # A fold-over covers its region three times (+, -, + orientation): rasterizing each
    # orientation in both drawing orders keeps ids of up to two layers of each.
    t = texcoords[faces]
    area = (t[:, 1, 0] - t[:, 0, 0]) * (t[:, 2, 1] - t[:, 0, 1]) - (t[:, 1, 1] - t[:, 0, 1]) * (t[:, 2, 0] - t[:, 0, 0])
    buffers = []
    for group in (np.flatnonzero(area >= 0), np.flatnonzero(area < 0)):
        if not len(group):
            continue
        for order in (group, group[::-1]):
            ids = rasterize_uv(ctx, texcoords, faces[order], R, R, attributes=False).tri_id
            buffers.append(np.where(ids >= 0, order[np.maximum(ids, 0)], -1))
    ctx.release()

    col = np.clip(np.floor(points[:, 0] * R).astype(np.int64), 0, R - 1)
    row = np.clip(np.floor(points[:, 1] * R).astype(np.int64), 0, R - 1)
    offsets = np.arange(-radius, radius + 1)
    rows = np.clip(row[:, None, None] + offsets[None, :, None], 0, R - 1)
    cols = np.clip(col[:, None, None] + offsets[None, None, :], 0, R - 1)
    rows, cols = np.broadcast_arrays(rows, cols)
    cand = np.concatenate([ids[rows, cols].reshape(len(points), -1) for ids in buffers], axis=1)
    cand.sort(axis=1)
    keep = cand >= 0
    keep[:, 1:] &= cand[:, 1:] != cand[:, :-1]
    pi, slot = np.nonzero(keep)
    fi = cand[pi, slot]

    def contained(pi: np.ndarray, fi: np.ndarray):
        bary = barycentric_2d(points[pi], texcoords[faces[fi]])
        inside = np.all(bary >= -_INSIDE_EPS, axis=1) & np.all(np.isfinite(bary), axis=1)
        return pi[inside], fi[inside], bary[inside]

    hit_p, hit_f, hit_b = contained(pi, fi)
    # Slivers: grow the candidate set of unresolved points by the triangles around it.
    unresolved = np.setdiff1d(np.unique(pi), hit_p)
    if unresolved.size:
        n = int(faces.max()) + 1 if m else 0
        incidence = sp.csr_matrix((np.ones(3 * m), (np.repeat(np.arange(m), 3), faces.ravel())), shape=(m, n))
        face_ring = (incidence @ incidence.T).tocsr()
        sel = np.isin(pi, unresolved)
        local = np.searchsorted(unresolved, pi[sel])
        current = sp.csr_matrix((np.ones(sel.sum()), (local, fi[sel])), shape=(len(unresolved), m))
        for _ in range(2):
            current = (current @ face_ring).tocsr()
            lp, lf = current.nonzero()
            p2, f2, b2 = contained(unresolved[lp], lf.astype(np.int64))
            hit_p, hit_f, hit_b = np.concatenate([hit_p, p2]), np.concatenate([hit_f, f2]), np.concatenate([hit_b, b2])
            still = ~np.isin(unresolved, p2)
            if not still.any():
                break
            unresolved = unresolved[still]
            current = current[np.flatnonzero(still)]
    order = np.argsort(hit_p, kind="stable")
    return hit_p[order], hit_f[order], hit_b[order]


def _dedupe(vertex: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Mask keeping one of several hypotheses of a vertex at the same 3-D point."""
    order = np.lexsort((points[:, 0], vertex))
    v, p = vertex[order], points[order]
    same = np.zeros(len(order), bool)
    same[1:] = (v[1:] == v[:-1]) & (np.linalg.norm(p[1:] - p[:-1], axis=1) < _SAME_POINT_M)
    keep = np.ones(len(order), bool)
    keep[order[same]] = False
    return keep


def _visible(camera: Camera, raster, points: np.ndarray, face: np.ndarray, tolerance: float):
    """Which surface points a camera sees, and their pixels.

    A point is seen if one of the 2x2 pixels around its projection shows its own triangle,
    or if it is no deeper than the farthest surface those pixels show (relative slack):
    permissive at occlusion boundaries, where the observation is within a pixel of visible
    material anyway.
    """
    pixels, z = camera.project(points)
    W, H = camera.width, camera.height
    ok = (z > 0) & np.all(np.isfinite(pixels), axis=1)
    ok &= (pixels[:, 0] > -0.5) & (pixels[:, 0] < W - 0.5) & (pixels[:, 1] > -0.5) & (pixels[:, 1] < H - 0.5)
    u0 = np.floor(np.where(ok, pixels[:, 0], 0)).astype(np.int64)
    v0 = np.floor(np.where(ok, pixels[:, 1], 0)).astype(np.int64)
    own = np.zeros(len(points), bool)
    front = np.zeros(len(points))
    covered = np.zeros(len(points), bool)
    for du in (0, 1):
        for dv in (0, 1):
            u = np.clip(u0 + du, 0, W - 1)
            v = np.clip(v0 + dv, 0, H - 1)
            tri = raster.tri_id[v, u]
            cov = tri >= 0
            own |= tri == face
            covered |= cov
            front = np.maximum(front, np.where(cov, raster.depth[v, u], 0.0))
    seen = ok & (own | (covered & (z <= front * (1 + tolerance))))
    return seen, pixels


# -- step 2: triangulation ----------------------------------------------------------------

def _camera_arrays(cameras: list[Camera]):
    K = np.stack([c.K for c in cameras])
    R = np.stack([c.R for c in cameras])
    t = np.stack([c.t for c in cameras])
    return K, R, t


def triangulate_dlt(cameras: list[Camera], pixels: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Linear multi-view triangulation (DLT), vectorised over points.

    Rows are built in normalised camera coordinates (K⁻¹ x) for conditioning.

    Args:
        cameras: the C cameras.
        pixels: (N,C,2) OpenCV pixel observations (anything where weight is 0).
        weights: (N,C) 0/1 (or real) weights; ≥ 2 non-zero per point.

    Returns:
        (N,3) float64 points (NaN where degenerate).
    """
    K, R, t = _camera_arrays(cameras)
    P = np.concatenate([R, t[:, :, None]], axis=2)  # (C,3,4) cam_from_world
    pix = np.nan_to_num(np.asarray(pixels, dtype=np.float64))
    xn = (pix - K[None, :, :2, 2]) / np.stack([K[:, 0, 0], K[:, 1, 1]], 1)[None]
    xn[..., 0] -= xn[..., 1] * (K[None, :, 0, 1] / K[None, :, 0, 0])  # skew, usually 0
    rows_x = xn[..., 0:1] * P[None, :, 2] - P[None, :, 0]
    rows_y = xn[..., 1:2] * P[None, :, 2] - P[None, :, 1]
    A = np.concatenate([rows_x, rows_y], axis=1) * np.concatenate([weights, weights], axis=1)[..., None]
    _, _, vt = np.linalg.svd(A)
    X = vt[:, -1]
    with np.errstate(divide="ignore", invalid="ignore"):
        out = X[:, :3] / X[:, 3:4]
    out[~np.all(np.isfinite(out), axis=1)] = np.nan
    return out


def _project_all(K, R, t, X):
    """(N,3) points in C cameras -> pixels (N,C,2), camera coordinates (N,C,3)."""
    y = np.einsum("cij,nj->nci", R, X) + t[None]
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = y[..., :2] / y[..., 2:3]
    pix = np.stack([K[:, 0, 0] * xy[..., 0] + K[:, 0, 1] * xy[..., 1] + K[:, 0, 2],
                    K[:, 1, 1] * xy[..., 1] + K[:, 1, 2]], axis=-1)
    return pix, y


def reprojection_errors(cameras: list[Camera], points: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """(N,C) pixel distance between the projections of points (N,3) and pixels (N,C,2)."""
    K, R, t = _camera_arrays(cameras)
    pix, _ = _project_all(K, R, t, np.asarray(points, dtype=np.float64))
    return np.linalg.norm(pix - pixels, axis=-1)


def refine_points(cameras: list[Camera], points: np.ndarray, pixels: np.ndarray, weights: np.ndarray,
                  iterations: int = 5) -> np.ndarray:
    """Gauss-Newton on the summed squared reprojection error, vectorised over points.

    Args:
        points: (N,3) initial points. pixels: (N,C,2). weights: (N,C) 0/1.

    Returns:
        (N,3) float64 refined points (a step that does not lower the error is not taken).
    """
    K, R, t = _camera_arrays(cameras)
    X = np.array(points, dtype=np.float64)
    pixels = np.nan_to_num(np.asarray(pixels, dtype=np.float64))
    w = np.asarray(weights, dtype=np.float64)

    def cost(X):
        pix, y = _project_all(K, R, t, X)
        r = np.nan_to_num(pix - pixels, nan=1e6) * w[..., None]
        return np.sum(r ** 2, axis=(1, 2)), pix, y

    c0, pix, y = cost(X)
    for _ in range(iterations):
        r = (pix - pixels) * w[..., None]  # (N,C,2)
        z = y[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            # d(pixel)/dX: f * (R_row - (y_row / z) R_2) / z, row by row (skew ignored: 0 in rigs).
            ju = K[None, :, 0, 0, None] * (R[None, :, 0] - (y[..., 0] / z)[..., None] * R[None, :, 2]) / z[..., None]
            jv = K[None, :, 1, 1, None] * (R[None, :, 1] - (y[..., 1] / z)[..., None] * R[None, :, 2]) / z[..., None]
        J = np.stack([ju, jv], axis=2) * w[..., None, None]  # (N,C,2,3)
        J = np.nan_to_num(J)
        JtJ = np.einsum("ncki,nckj->nij", J, J) + 1e-12 * np.eye(3)
        Jtr = np.einsum("ncki,nck->ni", J, np.nan_to_num(r))
        try:
            delta = -np.linalg.solve(JtJ, Jtr[..., None])[..., 0]
        except np.linalg.LinAlgError:
            delta = -np.stack([np.linalg.lstsq(a, b, rcond=None)[0] for a, b in zip(JtJ, Jtr)])
        X_new = X + delta
        c1, pix1, y1 = cost(X_new)
        better = np.isfinite(c1) & (c1 < c0)
        X[better], c0[better] = X_new[better], c1[better]
        pix[better], y[better] = pix1[better], y1[better]
        if not better.any():
            break
    return X


def _triangulate(cameras, pixels, weights, iterations):
    X = triangulate_dlt(cameras, pixels, weights)
    good = np.all(np.isfinite(X), axis=1)
    if good.any():
        X[good] = refine_points(cameras, X[good], pixels[good], weights[good], iterations)
    return X


def _surface_distance(points: np.ndarray, positions: np.ndarray, faces: np.ndarray, k: int = 8) -> np.ndarray:
    """Distance (N,) from points to a triangle mesh, over the triangles around the k nearest
    vertices (exact wherever the closest triangle has a vertex among them)."""
    import trimesh.triangles
    from scipy.spatial import cKDTree

    if len(points) == 0:
        return np.zeros(0)
    n = len(positions)
    faces = np.asarray(faces, dtype=np.int64)
    k = min(k, n)
    _, near = cKDTree(positions).query(points, k=k)
    near = np.asarray(near).reshape(len(points), k)
    # vertex -> incident faces, padded with -1.
    order = np.argsort(faces.ravel(), kind="stable")
    vert = faces.ravel()[order]
    face_of = order // 3
    counts = np.bincount(vert, minlength=n)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    width = int(counts.max())
    table = np.full((n, width), -1, dtype=np.int64)
    slot = np.arange(len(vert)) - start[vert]
    table[vert, slot] = face_of
    cand = table[near].reshape(len(points), -1)
    pi, ci = np.nonzero(cand >= 0)
    tris = positions[faces[cand[pi, ci]]]
    closest = trimesh.triangles.closest_point(tris, points[pi])
    d = np.linalg.norm(closest - points[pi], axis=1)
    out = np.full(len(points), np.inf)
    np.minimum.at(out, pi, d)
    return out


# -- steps 3 and 5: filling and smoothing ------------------------------------------------

def _fill(faces: np.ndarray, positions: np.ndarray, values: np.ndarray, assigned: np.ndarray,
          groups: np.ndarray) -> np.ndarray:
    if not assigned.any():
        return np.zeros_like(values)
    if assigned.all():
        return values.copy()
    from .extrapolate import fill

    return np.asarray(fill(faces, positions, values, assigned, method="harmonic", groups=groups), dtype=np.float64)


def taubin_smooth(values: np.ndarray, adjacency: sp.csr_matrix, iterations: int = 10, lam: float = 0.5,
                  mu: float = -0.53) -> np.ndarray:
    """Taubin's lambda/mu smoothing of per-vertex values (n,C): low-pass without shrinkage.

    Args:
        adjacency: (n,n) vertex adjacency (welded across seams).
    """
    deg = np.asarray(adjacency.sum(axis=1)).ravel()
    avg = sp.diags(1.0 / np.maximum(deg, 1)) @ adjacency
    out = np.array(values, dtype=np.float64)
    has = deg > 0
    for _ in range(int(iterations)):
        for step in (lam, mu):
            delta = avg @ out - out
            out[has] += step * delta[has]
    return out


# -- the whole reconstruction ---------------------------------------------------------------

def reconstruct(gt_uv: np.ndarray, inferred_positions: np.ndarray, faces: np.ndarray, uv: np.ndarray,
                texcoords: dict[str, np.ndarray], rig: Rig, options: ReconOptions = ReconOptions(), *,
                gt_faces: np.ndarray | None = None, assigned: dict[str, np.ndarray] | None = None,
                progress: bool = False) -> Reconstruction:
    """Triangulate the gt vertices from per-camera texture coordinates of an inferred mesh.

    Args:
        gt_uv: (n,2) T_G of the gt mesh's vertices.
        inferred_positions: (n',3) X_N on the texcoord set's (possibly subdivided) mesh; its
            first n vertices are the gt mesh's vertices (DESIGN §4 `parent`).
        faces: (m',3) int faces of the texcoord set's mesh.
        uv: (n',2) T_G on the texcoord set's mesh (checked for shape).
        texcoords: camera name -> (n',2) T_N of that camera; ≥ 2 cameras of `rig`.
        rig: the cameras (those named in `texcoords` are used).
        options: see ReconOptions.
        gt_faces: (m,3) faces of the gt mesh (needed to fill and smooth when n' > n;
            defaults to `faces` when n' == n).
        assigned: optional camera name -> (n',) bool (used with options.require_assigned).
        progress: show a progress bar over cameras.

    Returns:
        Reconstruction on the n gt vertices.
    """
    from tqdm import tqdm

    from .raster import GLContext, rasterize

    ctx = GLContext()
    gt_uv = np.asarray(gt_uv, dtype=np.float64)
    X_N = np.asarray(inferred_positions, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    n, n_sub = len(gt_uv), len(X_N)
    if gt_uv.shape != (n, 2) or X_N.shape != (n_sub, 3) or np.shape(uv) != (n_sub, 2) or n_sub < n:
        raise ValueError(f"shapes: gt_uv {gt_uv.shape} (n,2), inferred_positions {X_N.shape} (n',3), "
                         f"uv {np.shape(uv)} (n',2) with n' >= n")
    if gt_faces is None:
        if n_sub != n:
            raise ValueError("gt_faces is needed when the texcoord mesh is subdivided (n' > n)")
        gt_faces = faces
    gt_faces = np.asarray(gt_faces, dtype=np.int64)
    names = [c for c in rig.names if c in texcoords]
    if len(names) < 2:
        raise ValueError(f"reconstruction needs texcoords of ≥ 2 rig cameras, got {sorted(texcoords)}")
    cameras = [rig[c] for c in names]
    C = len(cameras)
    stats: dict[str, Any] = {"hypotheses": 0, "occluded": 0, "unassigned": 0, "ambiguous_observations": 0,
                             "ambiguous_vertices": 0, "outlier_observations": 0}

    # Steps 1-2 per camera: hypotheses (vertex, camera, pixel).
    hyp_v, hyp_c, hyp_px = [], [], []
    for c, cam in enumerate(tqdm(cameras, desc="locate", unit="camera", disable=not progress, leave=False)):
        T = np.asarray(texcoords[cam.name], dtype=np.float64)
        if T.shape != (n_sub, 2):
            raise ValueError(f"texcoords[{cam.name!r}] has shape {T.shape}, expected {(n_sub, 2)}")
        vi, fi, bary = locate_uv(gt_uv, faces, T, options.uv_resolution)
        stats["hypotheses"] += len(vi)
        if options.require_assigned and assigned is not None and cam.name in assigned:
            ok = np.all(np.asarray(assigned[cam.name], bool)[faces[fi]], axis=1)
            stats["unassigned"] += int((~ok).sum())
            vi, fi, bary = vi[ok], fi[ok], bary[ok]
        P = np.einsum("hk,hkj->hj", bary, X_N[faces[fi]])
        keep = _dedupe(vi, P)
        vi, fi, P = vi[keep], fi[keep], P[keep]
        raster = rasterize(ctx, X_N, faces, cam)
        seen, pixels = _visible(cam, raster, P, fi, options.depth_tolerance)
        stats["occluded"] += int((~seen).sum())
        hyp_v.append(vi[seen])
        hyp_c.append(np.full(int(seen.sum()), c))
        hyp_px.append(pixels[seen])
    ctx.release()
    hv, hc, hpx = np.concatenate(hyp_v), np.concatenate(hyp_c), np.concatenate(hyp_px)

    # Per (vertex, camera): how many hypotheses.
    count = np.zeros((n, C), dtype=np.int64)
    np.add.at(count, (hv, hc), 1)
    pixels = np.full((n, C, 2), np.nan)
    single = count[hv, hc] == 1
    pixels[hv[single], hc[single]] = hpx[single]
    weights = (count == 1).astype(np.float64)
    views = (count > 0).sum(axis=1)
    candidates = np.flatnonzero(views >= 2)
    ambiguous = candidates[np.any(count[candidates] > 1, axis=1)]
    stats["ambiguous_vertices"] = int(len(ambiguous))
    stats["ambiguous_observations"] = int(np.sum(count > 1))

    # Ambiguous vertices: resolve each multi-hypothesis camera by the least ray disagreement.
    if len(ambiguous):
        order = np.lexsort((hc, hv))
        hv_s, hc_s, hpx_s = hv[order], hc[order], hpx[order]
        starts = np.searchsorted(hv_s, ambiguous, side="left")
        stops = np.searchsorted(hv_s, ambiguous, side="right")
        unambiguous = (count[ambiguous] == 1).sum(axis=1)
        # Vertices with ≥ 2 single-hypothesis cameras: triangulate from those first.
        seeded = unambiguous >= 2
        X0 = np.full((len(ambiguous), 3), np.nan)
        if seeded.any():
            rows = ambiguous[seeded]
            X0[seeded] = _triangulate(cameras, pixels[rows], weights[rows], options.refine_iterations)
        for j, v in enumerate(ambiguous):
            sel = slice(starts[j], stops[j])
            cams_v, px_v = hc_s[sel], hpx_s[sel]
            multi = [c for c in np.unique(cams_v) if count[v, c] > 1]
            if not seeded[j]:
                X0[j] = _best_combination(cameras, v, cams_v, px_v, count[v], options)
            if not np.all(np.isfinite(X0[j])):
                continue
            for c in multi:
                opts = px_v[cams_v == c]
                projected, _ = cameras[c].project(X0[j])
                pick = int(np.argmin(np.linalg.norm(opts - projected, axis=1)))
                pixels[v, c] = opts[pick]
                weights[v, c] = 1.0

    # Robust triangulation of every vertex seen at least twice: drop the worst observation
    # while it exceeds the threshold and ≥ 3 remain.
    rows = np.flatnonzero(weights.sum(axis=1) >= 2)
    X = np.full((n, 3), np.nan)
    if len(rows):
        X[rows] = _triangulate(cameras, pixels[rows], weights[rows], options.refine_iterations)
        todo = rows
        for _ in range(C):
            err = reprojection_errors(cameras, X[todo], pixels[todo])
            err = np.where(weights[todo] > 0, np.nan_to_num(err, nan=np.inf), -1.0)
            worst = np.argmax(err, axis=1)
            bad = (err[np.arange(len(todo)), worst] > options.max_reprojection_px) & (weights[todo].sum(axis=1) >= 3)
            if not bad.any():
                break
            todo = todo[bad]
            weights[todo, worst[bad]] = 0.0
            stats["outlier_observations"] += int(bad.sum())
            X[todo] = _triangulate(cameras, pixels[todo], weights[todo], options.refine_iterations)

    rejected = {"fewer_than_2_views": int(n - len(rows)), "reprojection": 0, "surface_distance": 0,
                "cheirality": 0}
    triangulated = np.zeros(n, bool)
    if len(rows):
        finite = np.all(np.isfinite(X[rows]), axis=1)
        _, y = _project_all(*_camera_arrays(cameras), np.nan_to_num(X[rows]))
        in_front = finite & np.all((y[..., 2] > 0) | (weights[rows] == 0), axis=1)
        rejected["cheirality"] = int((~in_front).sum())
        err = reprojection_errors(cameras, np.nan_to_num(X[rows]), pixels[rows])
        err = np.where(weights[rows] > 0, np.nan_to_num(err, nan=np.inf), 0.0).max(axis=1)
        reproj_ok = in_front & (err <= options.max_reprojection_px)
        rejected["reprojection"] = int((in_front & ~reproj_ok).sum())
        dist = np.full(len(rows), np.inf)
        dist[reproj_ok] = _surface_distance(X[rows[reproj_ok]], X_N, faces)
        near = reproj_ok & (dist <= options.max_surface_distance_m)
        rejected["surface_distance"] = int((reproj_ok & ~near).sum())
        triangulated[rows[near]] = True

    # Seam copies (split vertices at one position) are one physical point: pool them.
    base = X_N[:n]
    groups = weld_groups(base)
    disp = np.zeros((n, 3))
    disp[triangulated] = X[triangulated] - base[triangulated]
    sums = np.zeros((n, 3))
    cnt = np.zeros(n)
    np.add.at(sums, groups[triangulated], disp[triangulated])
    np.add.at(cnt, groups[triangulated], 1.0)
    known = cnt[groups] > 0
    disp[known] = sums[groups[known]] / cnt[groups[known], None]
    stats["seam_copies_pooled"] = int((known & ~triangulated).sum())

    # Step 3: harmonic extension of the displacement to the rest.
    disp = _fill(gt_faces, base, disp, known, groups)
    points = base + disp
    unsmoothed = None
    if options.smooth:
        unsmoothed = points
        adj = welded_adjacency(gt_faces, groups)
        points = base + taubin_smooth(disp, adj, options.smooth_iterations)

    obs = {}
    for c, name in enumerate(names):
        o = np.where((weights[:, c] > 0)[:, None] & triangulated[:, None], pixels[:, c], np.nan)
        obs[name] = o
    err = reprojection_errors(cameras, points, np.stack([obs[name] for name in names], axis=1))
    used = np.isfinite(err)
    with np.errstate(invalid="ignore"):
        per_vertex = np.where(triangulated, np.nansum(err, axis=1) / np.maximum(used.sum(axis=1), 1), np.nan)
    return Reconstruction(points=points, inferred=base, triangulated=triangulated, observations=obs,
                          reprojection_error=per_vertex, rejected=rejected, stats=stats, unsmoothed=unsmoothed)


def _best_combination(cameras, vertex, cams_v, px_v, count_v, options) -> np.ndarray:
    """The point from the combination of one hypothesis per camera whose rays agree best.

    Cameras with the fewest hypotheses enter the enumeration first, while the number of
    combinations stays within options.max_combinations; the rest are resolved afterwards
    against the resulting point (by the caller).
    """
    cams = sorted(np.unique(cams_v), key=lambda c: count_v[c])
    chosen, total = [], 1
    for c in cams:
        if total * count_v[c] > options.max_combinations and len(chosen) >= 2:
            break
        chosen.append(c)
        total *= count_v[c]
    if len(chosen) < 2:
        return np.full(3, np.nan)
    choices = [np.flatnonzero(cams_v == c) for c in chosen]
    combos = np.array(list(itertools.islice(itertools.product(*choices), options.max_combinations)))
    sub = [cameras[c] for c in chosen]
    pix = px_v[combos]  # (k, len(chosen), 2)
    w = np.ones(combos.shape)
    X = triangulate_dlt(sub, pix, w)
    err = reprojection_errors(sub, np.nan_to_num(X), pix)
    cost = np.where(np.all(np.isfinite(X), axis=1), np.sum(err ** 2, axis=1), np.inf)
    best = int(np.argmin(cost))
    if not np.isfinite(cost[best]):
        return np.full(3, np.nan)
    return refine_points(sub, X[best:best + 1], pix[best:best + 1], w[best:best + 1], options.refine_iterations)[0]


# -- step 4: the command: report and files ---------------------------------------------------

def _rmse(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float | None:
    d = np.linalg.norm(np.asarray(a, np.float64) - np.asarray(b, np.float64), axis=1)
    if mask is not None:
        d = d[mask]
    return float(np.sqrt(np.mean(d ** 2))) if d.size else None


def strain_energies(positions: np.ndarray, rest: np.ndarray, faces: np.ndarray) -> dict[str, float]:
    """Compression and extension energies of a mesh against its rest shape.

    With s = len/rest_len - 1 per edge: compression = Σ_{s<0} s² / #edges, extension =
    Σ_{s>0} s² / #edges; also the mean |s|.
    """
    s = edge_strain(positions, rest, edges(faces))
    return {"compression": float(np.sum(np.minimum(s, 0) ** 2) / len(s)),
            "extension": float(np.sum(np.maximum(s, 0) ** 2) / len(s)),
            "mean_abs_strain": float(np.mean(np.abs(s)))}


def _colormap(values: np.ndarray, vmin: float, vmax: float, name: str) -> np.ndarray:
    """(n,) values -> (n,3) uint8 colours of a matplotlib colormap over [vmin, vmax]."""
    import matplotlib

    x = np.clip((np.asarray(values, np.float64) - vmin) / (vmax - vmin), 0, 1)
    return (matplotlib.colormaps[name](x)[:, :3] * 255 + 0.5).astype(np.uint8)


def error_colors(error_m: np.ndarray, scale_m: float) -> np.ndarray:
    """Per-vertex error heatmap (n,3) uint8: blue at 0, red at ≥ scale_m."""
    return _colormap(error_m, 0.0, scale_m, "jet")


def strain_colors(strain: np.ndarray, scale: float) -> np.ndarray:
    """Signed strain -> (n,3) uint8: compression blue, 0 white, extension red (±scale saturates)."""
    return _colormap(strain, -scale, scale, "bwr")


def texture_colors(uv: np.ndarray, size: int = 1024) -> np.ndarray:
    """The fabric texture's colour at each texture coordinate (n,2) -> (n,3) uint8 (nearest texel)."""
    from .raster import fabric_colors

    return fabric_colors(uv, size)


def render_vertex_colors(positions: np.ndarray, faces: np.ndarray, colors: np.ndarray, camera: Camera,
                         background: tuple[int, int, int] = (40, 40, 46)) -> np.ndarray:
    """Per-vertex colours (n,3) uint8, interpolated and shaded (|cos| of the camera-space normal).

    Returns:
        (H,W,3) uint8 RGB image.
    """
    from .mesh import vertex_normals
    from .raster import GLContext, interpolate, rasterize

    with GLContext() as ctx:
        raster = rasterize(ctx, positions, faces, camera)
    normals = vertex_normals(positions, faces, weld_groups(positions)) @ camera.R.T
    shade = 0.35 + 0.65 * np.abs(interpolate(normals, raster, faces)[..., 2:3])
    rgb = interpolate(np.asarray(colors, np.float64), raster, faces) * shade
    img = np.where(raster.mask[..., None], rgb, np.asarray(background, np.float64))
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)


def comparison_picture(camera: Camera, faces: np.ndarray, uv: np.ndarray, gt: np.ndarray, inferred: np.ndarray,
                       reconstructed: np.ndarray, rest: np.ndarray | None, options: ReconOptions = ReconOptions(),
                       triangulated: np.ndarray | None = None) -> np.ndarray:
    """gt / inferred / reconstruction side by side from one camera: textured (T_G), signed
    strain vs rest (if given) and the error ‖x - gt‖ heatmap.

    Returns:
        (H',W',3) uint8 RGB picture.
    """
    from .viz import grid_image
    from .raster import GLContext, render_textured

    meshes = {"gt": gt, "inferred": inferred, "reconstruction": reconstructed}
    with GLContext() as ctx:
        rows = [[render_textured(ctx, x, faces, uv, camera) for x in meshes.values()]]
    labels = ["texture"]
    if rest is not None:
        rows.append([render_vertex_colors(x, faces, strain_colors(vertex_strain_energy(x, rest, faces),
                                                                  options.strain_scale), camera)
                     for x in meshes.values()])
        labels.append(f"strain +-{options.strain_scale:g}")
    err_row = [render_vertex_colors(x, faces, error_colors(np.linalg.norm(x - gt, axis=1), options.error_scale_m),
                                    camera) for x in meshes.values()]
    if triangulated is not None:
        grey = np.where(triangulated[:, None], np.array([[60, 200, 90]]), np.array([[120, 120, 120]])).astype(np.uint8)
        err_row[0] = render_vertex_colors(gt, faces, grey, camera)
    rows.append(err_row)
    labels.append(f"error 0-{options.error_scale_m * 1e3:g}mm" + (" (gt: green = triangulated)" if triangulated is not None else ""))
    picture = grid_image(rows, col_labels=list(meshes), row_labels=labels)
    return picture


def triangulate_pose(dataset, rig: Rig, texcoords, pose: int, out: str | os.PathLike | None,
                     options: ReconOptions = ReconOptions(), progress: bool = True) -> dict:
    """`mvtex triangulate`: reconstruct one pose of a dataset from a texcoord set.

    Args:
        dataset: a `mvtex.dataset.Dataset`.
        rig: the cameras; those of the texcoord set are used (≥ 2 needed).
        texcoords: a `mvtex.texcoords.TexcoordSet` for this dataset.
        pose: dataset pose index (must be one of the texcoord set's poses).
        out: output directory (written atomically), or None for the numbers only:
            reconstruction.ply (gt connectivity, uv as s/t, error heatmap colours, uchar
            `triangulated`), colmap/{cameras,images,points3D}.bin, images/<camera>.png
            (the inferred mesh textured with that camera's T_N), comparison.png, report.json.
        options: see ReconOptions.
        progress: progress bars on stderr.

    Returns:
        The report (DESIGN §7): pose, num_vertices, num_triangulated, rmse_m{inferred,
        reconstructed}, rmse_triangulated_m{...}, mean_reprojection_error_px, plus
        cameras, rejected (vertex counts by reason), stats, strain_energy{gt, inferred,
        reconstructed} (None without a rest shape), smooth{...}, options.
    """
    pose = int(pose)
    if not 0 <= pose < dataset.num_poses:
        raise InputError(dataset.path, f"pose {pose} is outside [0, {dataset.num_poses})")
    texcoords.row(pose)  # InputError if the set lacks this pose
    if texcoords.num_base_vertices != dataset.num_vertices:
        raise InputError(texcoords.path / "mesh.npz", f"made for a mesh of {texcoords.num_base_vertices} vertices, "
                         f"the dataset has {dataset.num_vertices}")
    names = [c for c in texcoords.cameras if c in rig.names]
    if len(names) < 2:
        raise InputError(texcoords.path, f"triangulation needs ≥ 2 cameras present in both the texcoord set "
                         f"({', '.join(texcoords.cameras)}) and the rig ({', '.join(rig.names)})")
    sub_rig = rig.select(names)
    X_N = texcoords.positions(np.asarray(dataset.inferred[pose], np.float64))
    T = {c: np.asarray(texcoords.texcoords(c, pose), np.float64) for c in names}
    assigned = {c: texcoords.assigned(c, pose) for c in names}
    rec = reconstruct(dataset.uv, X_N, texcoords.faces, texcoords.uv, T, sub_rig, options,
                      gt_faces=dataset.faces, assigned=assigned, progress=progress)
    gt = np.asarray(dataset.gt[pose], np.float64)
    rest = None if dataset.rest is None else np.asarray(dataset.rest, np.float64)
    report = reconstruction_report(rec, gt, dataset.faces, rest, pose, options)
    report.update(cameras=names, texcoords=str(texcoords.path), source=texcoords.source, subdiv=texcoords.subdiv)
    if out is not None:
        export_reconstruction(out, rec, sub_rig, faces=dataset.faces, uv=dataset.uv, gt=gt, rest=rest,
                              inferred_mesh=(X_N, texcoords.faces, T), report=report, options=options,
                              progress=progress)
    return report


def reconstruction_report(rec: Reconstruction, gt: np.ndarray, faces: np.ndarray, rest: np.ndarray | None,
                          pose: int, options: ReconOptions = ReconOptions()) -> dict:
    """The JSON report of a reconstruction against the gt positions (n,3)."""
    tri = rec.triangulated
    err = rec.reprojection_error[tri]
    report: dict[str, Any] = {
        "pose": int(pose),
        "num_vertices": int(len(gt)),
        "num_triangulated": int(tri.sum()),
        "rmse_m": {"inferred": _rmse(rec.inferred, gt), "reconstructed": _rmse(rec.points, gt)},
        "rmse_triangulated_m": {"inferred": _rmse(rec.inferred, gt, tri), "reconstructed": _rmse(rec.points, gt, tri)},
        "mean_reprojection_error_px": float(np.mean(err)) if err.size else None,
        "rejected": dict(rec.rejected),
        "stats": dict(rec.stats),
        "strain_energy": None,
        "smooth": {"enabled": bool(options.smooth)},
    }
    if rest is not None:
        report["strain_energy"] = {k: strain_energies(x, rest, faces) for k, x in
                                   (("gt", gt), ("inferred", rec.inferred), ("reconstructed", rec.points))}
    if rec.unsmoothed is not None:
        report["smooth"].update(
            iterations=int(options.smooth_iterations),
            before={"rmse_m": _rmse(rec.unsmoothed, gt), "rmse_triangulated_m": _rmse(rec.unsmoothed, gt, tri),
                    "strain_energy": None if rest is None else strain_energies(rec.unsmoothed, rest, faces)})
    report["options"] = asdict(options)
    return report


def export_reconstruction(out: str | os.PathLike, rec: Reconstruction, rig: Rig, *, faces: np.ndarray,
                          uv: np.ndarray, gt: np.ndarray | None, rest: np.ndarray | None,
                          inferred_mesh: tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]] | None,
                          report: dict, options: ReconOptions = ReconOptions(), progress: bool = False) -> Path:
    """Write a reconstruction directory atomically (see `triangulate_pose` for the layout).

    Args:
        rec: the reconstruction; rig: its cameras (observations keyed by their names).
        faces, uv: gt mesh connectivity (m,3) and T_G (n,2).
        gt: (n,3) gt positions for the error colours and the comparison picture (None: grey).
        rest: (n,3) rest shape for the strain picture, or None.
        inferred_mesh: (X_N' (n',3), faces' (m',3), {camera: T_N (n',2)}) for images/<camera>.png.
        report: written as report.json.
    """
    from tqdm import tqdm

    from .colmap import point_reconstruction
    from .io import save_png
    from .ply import write_ply

    out = Path(out)
    names = [c for c in rig.names if c in rec.observations]
    tri_idx = np.flatnonzero(rec.triangulated)
    with _atomic_dir(out) as tmp:
        # PLY: gt connectivity, error heatmap colours.
        if gt is not None:
            colors = error_colors(np.linalg.norm(rec.points - gt, axis=1), options.error_scale_m)
        else:
            colors = np.full((len(rec.points), 3), 180, np.uint8)
        write_ply(tmp / "reconstruction.ply", rec.points, faces, uv=uv, colors=colors,
                  vertex_properties={"triangulated": rec.triangulated.astype(np.uint8)},
                  comments=(f"mvtex reconstruction, pose {report.get('pose')}",
                            f"colour: |reconstructed - gt| blue 0 .. red >= {options.error_scale_m} m"))
        # COLMAP model: one 3-D point per triangulated vertex.
        observations, tracks = {}, {}
        for name in names:
            o = rec.observations[name][tri_idx]
            seen = np.flatnonzero(np.isfinite(o[:, 0]))
            observations[name] = o[seen]
            track = np.full(len(tri_idx), -1, dtype=np.int64)
            track[seen] = np.arange(len(seen))
            tracks[name] = track
        model, _ = point_reconstruction(rig.select(names), observations, rec.points[tri_idx], tracks,
                                        texture_colors(np.asarray(uv)[tri_idx]))
        (tmp / "colmap").mkdir()
        model.write_binary(str(tmp / "colmap"))
        # Images of the texture-corrected inferred mesh, so COLMAP's GUI shows the model on them.
        if inferred_mesh is not None:
            from .raster import GLContext, render_textured

            X_sub, faces_sub, T = inferred_mesh
            (tmp / "images").mkdir()
            for name in tqdm(names, desc="images", unit="camera", disable=not progress, leave=False):
                with GLContext() as ctx:
                    save_png(tmp / "images" / f"{name}.png", render_textured(ctx, X_sub, faces_sub, T[name], rig[name]))
        if gt is not None:
            views = np.array([np.isfinite(rec.observations[c][:, 0]).sum() for c in names])
            camera = rig[names[int(np.argmax(views))]]
            save_png(tmp / "comparison.png", comparison_picture(camera, faces, uv, gt, rec.inferred, rec.points, rest,
                                                                options, rec.triangulated))
        from .io import write_json

        write_json(tmp / "report.json", report)
    return out


def _atomic_dir(path: Path):
    """`io.atomic_path` for a directory: yields the created temporary directory."""
    import contextlib

    from .io import atomic_path

    @contextlib.contextmanager
    def _ctx():
        with atomic_path(path) as tmp:
            tmp.mkdir()
            yield tmp

    return _ctx()
