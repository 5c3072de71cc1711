"""Where each camera shows each gt vertex's material: step 1 of the reconstruction.

Camera p sees the inferred mesh with texture coordinates T_N^p, so it shows material
T_G[i] at the projection of the inferred-surface point whose T_N^p equals T_G[i]:

- `locate_uv` finds every triangle whose T_N^p contains T_G[i] (UV-space id rasters in
  both orientations and drawing orders, so fold-overs give several hypotheses; exact
  float64 barycentrics decide);
- `collect_hypotheses` turns each into a 3-D point on the inferred mesh (same
  barycentrics of X_N), keeps it where the camera sees it (depth test against a raster of
  the inferred mesh; with a body, an exact ray cast against it) and records its pixel.

The GL rasters come from `mvtex.render.raster`; the rest of the reconstruction (`mvtex.recon.triangulate`)
needs no GL.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Sequence

import numpy as np
import scipy.sparse as sp
from tqdm import tqdm

from mvtex.data.camera import Camera
from mvtex.data.mesh import barycentric_2d
from mvtex.recon.geometry import in_image
from mvtex.render.context import GLContext, context_or_new
from mvtex.render.raster import rasterize, rasterize_uv
from mvtex.sliding.hits import nearest_body_hit
from mvtex.util.checks import check_shape

if TYPE_CHECKING:
    from mvtex.render.context import GLContext
    from mvtex.render.raster import Raster


# Barycentric slack for "contains": points on a shared edge belong to both triangles
# (the duplicate 3-D points are merged afterwards).
_INSIDE_EPS = 1e-7


# Two hypotheses of one (vertex, camera) closer than this (m) are the same point.
_SAME_POINT_M = 1e-8


def locate_uv(points: np.ndarray, faces: np.ndarray, texcoords: np.ndarray, resolution: int = 1024,
              radius: int = 1, *, ctx: GLContext | None = None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
        ctx: the GL context (`mvtex.render.context.GLContext`); one is made when None.

    Returns:
        point_index (h,) int64, face_index (h,) int64, bary (h,3) float64: one row per
        (point, containing triangle) pair, sorted by point.
    """

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
    with context_or_new(ctx) as ctx:
        for group in (np.flatnonzero(area >= 0), np.flatnonzero(area < 0)):
            if not len(group):
                continue
            for order in (group, group[::-1]):
                ids = rasterize_uv(ctx, texcoords, faces[order], R, R, attributes=False).tri_id
                buffers.append(np.where(ids >= 0, order[np.maximum(ids, 0)], -1))

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


def visible_points(camera: Camera, points: np.ndarray, face: np.ndarray, cloth: Raster,
                   occluders: Sequence[Raster] = (), tolerance: float = 0.005) -> tuple[np.ndarray, np.ndarray]:
    """Which points of the inferred surface a camera sees, and their pixels.

    Against the cloth's own raster, a point is seen if one of the 2x2 pixels around its
    projection shows its own triangle, or if it is no deeper than the farthest surface
    those pixels show (relative slack): permissive at occlusion boundaries, where the
    observation is within a pixel of visible material anyway. An occluder (another opaque
    surface rendered from the same camera, e.g. the wearer's body) hides a point where any
    of the 2x2 pixels shows it nearer than the point (same slack): strict, since an
    observation next to the body's silhouette may be of material the body hides.

    Args:
        camera: the camera the rasters were rendered from.
        points: (k,3) float64 surface points; face: (k,) int their triangles in `cloth`.
        cloth: `mvtex.render.raster.Raster` (with depth) of the inferred mesh.
        occluders: rasters (with depth) of further opaque surfaces.
        tolerance: relative depth slack.

    Returns:
        seen (k,) bool and pixels (k,2) float64 OpenCV pixels.
    """
    pixels, z = camera.project(points)
    W, H = camera.width, camera.height
    ok = (z > 0) & np.all(np.isfinite(pixels), axis=1) & in_image(pixels, W, H)
    u0 = np.floor(np.where(ok, pixels[:, 0], 0)).astype(np.int64)
    v0 = np.floor(np.where(ok, pixels[:, 1], 0)).astype(np.int64)
    own = np.zeros(len(points), bool)
    front = np.zeros(len(points))
    covered = np.zeros(len(points), bool)
    hidden = [np.zeros(len(points), bool) for _ in occluders]
    for du in (0, 1):
        for dv in (0, 1):
            u = np.clip(u0 + du, 0, W - 1)
            v = np.clip(v0 + dv, 0, H - 1)
            tri = cloth.tri_id[v, u]
            cov = tri >= 0
            own |= tri == face
            covered |= cov
            front = np.maximum(front, np.where(cov, cloth.depth[v, u], 0.0))
            for k, occluder in enumerate(occluders):
                nearer = (occluder.tri_id[v, u] >= 0) & (occluder.depth[v, u] * (1 + tolerance) < z)
                hidden[k] |= nearer
    seen = ok & (own | (covered & (z <= front * (1 + tolerance))))
    for h in hidden:
        seen &= ~h
    return seen, pixels


@dataclass(frozen=True)
class Hypotheses:
    """Candidate observations of gt vertices, one row per (vertex, camera, located triangle).

    Attributes:
        vertex: (h,) int64 gt vertex index.
        camera: (h,) int64 index into the reconstruction's camera list.
        pixel: (h,2) float64 OpenCV pixel of the located surface point in that camera.
        face: (h,) int64 the triangle of the texcoord set's mesh it was located in.
        bary: (h,3) float64 its barycentrics there (of T_N, and so of X_N).
        sigma: (h,) float64 the standard deviation (m) of the located 3-D point that the
            texcoords' predictive uncertainty implies (`located_sigma`), or None when the
            texcoord set reports none.
    """

    vertex: np.ndarray
    camera: np.ndarray
    pixel: np.ndarray
    face: np.ndarray
    bary: np.ndarray
    sigma: np.ndarray | None = None

    def subset(self, keep: np.ndarray) -> "Hypotheses":
        """The hypotheses selected by a (h,) bool mask or an index array."""
        return Hypotheses(self.vertex[keep], self.camera[keep], self.pixel[keep], self.face[keep], self.bary[keep],
                          None if self.sigma is None else self.sigma[keep])


def located_sigma(positions: np.ndarray, faces: np.ndarray, texcoords: np.ndarray, uncertainty: np.ndarray,
                  face: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """How far (m, a standard deviation) a located point may be off, given the texcoords'
    per-vertex predictive standard deviation.

    A point is located where T_N equals a material coordinate; an error e of T_N there
    moves it by J e, J = dX/dT_N (3x2) the triangle's map from texture coordinates to
    space. With an isotropic error of expected squared length σ² (σ interpolated
    barycentrically from the triangle's corners), the point's expected squared shift is
    σ² ‖J‖_F² / 2. A triangle whose T_N is degenerate gives infinity.

    Args:
        positions: (n',3) X_N; faces: (m',3); texcoords: (n',2) T_N of the camera.
        uncertainty: (n',) the standard deviation of T_N (uv units).
        face: (h,) triangles; bary: (h,3) barycentrics of the located points.

    Returns:
        (h,) float64.
    """
    f = faces[face]
    X, T = positions[f], texcoords[f]
    dX = np.stack([X[:, 1] - X[:, 0], X[:, 2] - X[:, 0]], axis=2)  # (h,3,2)
    dT = np.stack([T[:, 1] - T[:, 0], T[:, 2] - T[:, 0]], axis=2)  # (h,2,2)
    det = dT[:, 0, 0] * dT[:, 1, 1] - dT[:, 0, 1] * dT[:, 1, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.stack([np.stack([dT[:, 1, 1], -dT[:, 0, 1]], 1), np.stack([-dT[:, 1, 0], dT[:, 0, 0]], 1)], 1) / \
            det[:, None, None]
        J = np.einsum("hij,hjk->hik", dX, inv)
        norm = np.sqrt(np.sum(J ** 2, axis=(1, 2)) / 2)
    sigma_uv = np.einsum("hk,hk->h", bary, np.asarray(uncertainty, np.float64)[f])
    out = sigma_uv * norm
    return np.where(np.isfinite(out) & (det != 0), out, np.inf)


def collect_hypotheses(gt_uv: np.ndarray, inferred_positions: np.ndarray, faces: np.ndarray,
                       texcoords: dict[str, np.ndarray], cameras: Sequence[Camera], *, uv_resolution: int = 1024,
                       depth_tolerance: float = 0.005, assigned: dict[str, np.ndarray] | None = None,
                       require_assigned: bool = True, body: tuple[np.ndarray, np.ndarray] | None = None,
                       uncertainty: dict[str, np.ndarray] | None = None, progress: bool = False,
                       ctx: GLContext | None = None) -> tuple[Hypotheses, dict[str, int]]:
    """Per camera, the surface points showing each gt vertex's material, where visible.

    Args:
        gt_uv: (n,2) T_G of the gt vertices.
        inferred_positions: (n',3) X_N; faces: (m',3) int of the texcoord set's mesh.
        texcoords: camera name -> (n',2) T_N of that camera (every camera of `cameras`).
        cameras: the C cameras.
        uv_resolution: texels per side of the UV lookup buffer (`locate_uv`).
        depth_tolerance: relative depth slack of the visibility test.
        assigned: optional camera name -> (n',) bool (which vertices' T_N were assigned
            rather than extrapolated).
        require_assigned: with `assigned`, drop hypotheses in triangles with an
            unassigned corner.
        body: optional (positions (nb,3), faces (mb,3)) of the wearer's body in this pose:
            a hypothesis whose ray from the camera meets the body before the point (an
            exact float64 ray cast, `mvtex.sliding.hits.nearest_body_hit`) is not kept.
        uncertainty: optional camera name -> (n',) predictive standard deviation of that
            camera's T_N (uv units), for every camera: the hypotheses then carry `sigma`
            (`located_sigma`).
        progress: progress bar over cameras on stderr.
        ctx: the GL context (`mvtex.render.context.GLContext`); one is made when None.

    Returns:
        The visible hypotheses, and counts: "hypotheses" located, and of them
        "unassigned" (dropped for an unassigned corner), "duplicate" (the same 3-D point as
        another of the vertex's hypotheses in that camera: a point on a shared edge),
        "occluded" (by the cloth) and "hidden_by_body" (seen past the cloth, not past the body).
    """

    if ctx is None:
        with GLContext() as own:
            return collect_hypotheses(gt_uv, inferred_positions, faces, texcoords, cameras, uv_resolution=uv_resolution,
                                      depth_tolerance=depth_tolerance, assigned=assigned,
                                      require_assigned=require_assigned, body=body, uncertainty=uncertainty,
                                      progress=progress, ctx=own)
    X_N = np.asarray(inferred_positions, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    counts = {"hypotheses": 0, "unassigned": 0, "duplicate": 0, "occluded": 0, "hidden_by_body": 0}
    if body is not None:
        body_positions = np.asarray(body[0], dtype=np.float64)
        body_faces = np.asarray(body[1], dtype=np.int64)
        check_shape(body_positions, "body positions", ("nb", 3))
        check_shape(body_faces, "body faces", ("mb", 3))
    if uncertainty is not None and any(cam.name not in uncertainty for cam in cameras):
        uncertainty = None  # every camera's or none
    hyp_v, hyp_c, hyp_px, hyp_f, hyp_b, hyp_s = [], [], [], [], [], []
    for c, cam in enumerate(tqdm(cameras, desc="locate", unit="camera", disable=not progress, leave=False)):
        T = np.asarray(texcoords[cam.name], dtype=np.float64)
        check_shape(T, f"texcoords[{cam.name!r}]", (len(X_N), 2))
        vi, fi, bary = locate_uv(gt_uv, faces, T, uv_resolution, ctx=ctx)
        counts["hypotheses"] += len(vi)
        if require_assigned and assigned is not None and cam.name in assigned:
            ok = np.all(np.asarray(assigned[cam.name], bool)[faces[fi]], axis=1)
            counts["unassigned"] += int((~ok).sum())
            vi, fi, bary = vi[ok], fi[ok], bary[ok]
        P = np.einsum("hk,hkj->hj", bary, X_N[faces[fi]])
        keep = _dedupe(vi, P)
        counts["duplicate"] += int((~keep).sum())
        vi, fi, bary, P = vi[keep], fi[keep], bary[keep], P[keep]
        raster = rasterize(ctx, X_N, faces, cam)
        seen, pixels = visible_points(cam, P, fi, raster, tolerance=depth_tolerance)
        counts["occluded"] += int((~seen).sum())
        if body is not None:
            # The body hides the point when the ray from the camera meets it before the
            # point: an exact ray cast, the rule of texture sliding's depth test.
            hidden = np.zeros(len(P), bool)
            hidden[seen] = nearest_body_hit(cam, body_positions, body_faces, P[seen]) < 1
            counts["hidden_by_body"] += int(hidden.sum())
            seen &= ~hidden
        hyp_v.append(vi[seen])
        hyp_c.append(np.full(int(seen.sum()), c))
        hyp_px.append(pixels[seen])
        hyp_f.append(fi[seen])
        hyp_b.append(bary[seen])
        if uncertainty is not None:
            u = np.asarray(uncertainty[cam.name], dtype=np.float64)
            check_shape(u, f"uncertainty[{cam.name!r}]", (len(X_N),))
            hyp_s.append(located_sigma(X_N, faces, T, u, fi[seen], bary[seen]))
    return Hypotheses(np.concatenate(hyp_v), np.concatenate(hyp_c), np.concatenate(hyp_px), np.concatenate(hyp_f),
                      np.concatenate(hyp_b), np.concatenate(hyp_s) if uncertainty is not None else None), counts
