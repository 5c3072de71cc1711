"""Multi-view 3-D reconstruction from a texcoord set (DESIGN §5 "Reconstruction").

Every gt vertex i carries its material coordinate T_G[i]. Camera p sees the inferred mesh
with texture coordinates T_N^p; the pixel where p shows material T_G[i] is therefore the
projection of the inferred-surface point whose T_N^p equals T_G[i]. `reconstruct` runs
these steps, each a function of its own:

1. `mvtex.recon.locate.collect_hypotheses`: per camera, *locate* T_G[i] in the UV image of the
   inferred mesh (`locate_uv`: every triangle whose T_N^p contains it is a hypothesis,
   texcoords may fold over); the same barycentric combination of the inferred positions
   X_N is a 3-D point, kept where camera p sees it (depth test against a raster of the
   inferred mesh); its projection is the observation.
2. `resolve_ambiguity`: where a camera holds several hypotheses of one vertex, keep the
   one nearest to the point of the combination whose rays disagree least.
3. `triangulate_observations`: every vertex seen by ≥ 2 cameras is triangulated (the
   engine: `mvtex.recon.geometry.triangulate_points`, DLT + Gauss-Newton, or COLMAP through
   `mvtex.formats.colmap.triangulate_tracks`), dropping its worst observation while it exceeds the
   reprojection threshold.
4. `accept_points`: reject points behind a camera, with implausible reprojection error or
   far from the inferred surface.
5. `pool_and_fill`: seam copies pool their displacement; vertices not triangulated get X_N
   plus a harmonic extension of it (`extrapolate.fill`); optional Taubin smoothing.

Step 1 is the only one that rasterizes (GL, in `mvtex.recon.locate`); the geometry of the
others is `mvtex.recon.geometry` (NumPy).
`triangulate_pose` is the `mvtex triangulate` command for one dataset pose; writing its
output directory is `mvtex.recon.export`.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from functools import partial
from typing import TYPE_CHECKING, Any, Callable, Sequence

import numpy as np
import scipy.sparse as sp

from mvtex.data.camera import Camera
from mvtex.data.mesh import weld_groups, welded_adjacency
from mvtex.data.rig import Rig
from mvtex.recon.geometry import (
    least_disagreement,
    project_points,
    refine_points,
    reprojection_errors,
    surface_distance,
    triangulate_points,
)
from mvtex.recon.locate import Hypotheses, collect_hypotheses
from mvtex.util.checks import check_shape

if TYPE_CHECKING:
    from mvtex.render.context import GLContext


# Triangulation engines of `ReconOptions.engine`.
ENGINES = ("mvtex", "pycolmap")


# A triangulation engine: (cameras, pixels (N,C,2), weights (N,C)) -> points (N,3), NaN where degenerate.
Triangulator = Callable[[Sequence[Camera], np.ndarray, np.ndarray], np.ndarray]


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
        refine_iterations: Gauss-Newton steps after the DLT (engine "mvtex", and the
            hypothesis choice of both engines).
        error_scale_m: error heatmaps run from blue (0) to red (≥ this).
        strain_scale: strain pictures run from blue (-this, compression) to red (+this).
        engine: who triangulates the tracks: "mvtex" (vectorised DLT + Gauss-Newton, the
            default: faster) or "pycolmap" (COLMAP's multi-view triangulation + points-only
            bundle adjustment); both reach the same least-squares points.
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
    engine: str = "mvtex"

    def __post_init__(self) -> None:
        if self.engine not in ENGINES:
            raise ValueError(f"engine must be one of {', '.join(ENGINES)}, got {self.engine!r}")


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


def resolve_ambiguity(hypotheses: Hypotheses, num_vertices: int, cameras: Sequence[Camera],
                      options: ReconOptions = ReconOptions(), triangulate: Triangulator | None = None
                      ) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """Step 2: one observation per (vertex, camera), choosing among several hypotheses.

    A vertex with several hypotheses in some camera gets a reference point: triangulated
    (`triangulate`) from its single-hypothesis cameras where it has ≥ 2 of them, else the
    combination of one hypothesis per camera whose rays disagree least
    (`mvtex.recon.geometry.least_disagreement`, refined by Gauss-Newton). Each ambiguous camera
    then keeps the hypothesis nearest to the reference point's projection.

    Args:
        hypotheses: from `collect_hypotheses`.
        num_vertices: n, the number of gt vertices.
        cameras: the C cameras.
        options: max_combinations, refine_iterations.
        triangulate: the engine for the reference points (default: `track_triangulator(options)`).

    Returns:
        pixels (n,C,2) float64 (NaN where none), weights (n,C) float64 1 where camera c has
        an observation of vertex n, 0 where not, and counts {"ambiguous_observations",
        "ambiguous_vertices"}.
    """
    triangulate = track_triangulator(options) if triangulate is None else triangulate
    hv, hc, hpx = hypotheses.vertex, hypotheses.camera, hypotheses.pixel
    n, C = int(num_vertices), len(cameras)
    count = np.zeros((n, C), dtype=np.int64)
    np.add.at(count, (hv, hc), 1)
    pixels = np.full((n, C, 2), np.nan)
    single = count[hv, hc] == 1
    pixels[hv[single], hc[single]] = hpx[single]
    weights = (count == 1).astype(np.float64)
    views = (count > 0).sum(axis=1)
    candidates = np.flatnonzero(views >= 2)
    ambiguous = candidates[np.any(count[candidates] > 1, axis=1)]
    counts = {"ambiguous_observations": int(np.sum(count > 1)), "ambiguous_vertices": int(len(ambiguous))}
    if not len(ambiguous):
        return pixels, weights, counts

    order = np.lexsort((hc, hv))
    hv_s, hc_s, hpx_s = hv[order], hc[order], hpx[order]
    starts = np.searchsorted(hv_s, ambiguous, side="left")
    stops = np.searchsorted(hv_s, ambiguous, side="right")
    # Vertices with ≥ 2 single-hypothesis cameras: triangulate from those first.
    seeded = (count[ambiguous] == 1).sum(axis=1) >= 2
    X0 = np.full((len(ambiguous), 3), np.nan)
    if seeded.any():
        rows = ambiguous[seeded]
        X0[seeded] = triangulate(cameras, pixels[rows], weights[rows])
    for j, v in enumerate(ambiguous):
        sel = slice(starts[j], stops[j])
        cams_v, px_v = hc_s[sel], hpx_s[sel]
        if not seeded[j]:
            X0[j] = _least_disagreement_point(cameras, cams_v, px_v, count[v], options)
        if not np.all(np.isfinite(X0[j])):
            continue
        for c in np.unique(cams_v):
            if count[v, c] < 2:
                continue
            opts = px_v[cams_v == c]
            projected, _ = cameras[c].project(X0[j])
            pixels[v, c] = opts[int(np.argmin(np.linalg.norm(opts - projected, axis=1)))]
            weights[v, c] = 1.0
    return pixels, weights, counts


def _least_disagreement_point(cameras: Sequence[Camera], cams_v: np.ndarray, px_v: np.ndarray,
                              count_v: np.ndarray, options: ReconOptions) -> np.ndarray:
    """The point (3,) of the combination of one hypothesis per camera whose rays agree best.

    Cameras with the fewest hypotheses enter the enumeration first, while the number of
    combinations stays within options.max_combinations; the other cameras are resolved
    against the resulting point by the caller. NaN when no combination is usable.
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
    candidates = px_v[combos]  # (k, len(chosen), 2)
    best, point = least_disagreement(sub, candidates)
    if best < 0:
        return point
    return refine_points(sub, point[None], candidates[best:best + 1], np.ones((1, len(sub))),
                         options.refine_iterations)[0]


def track_triangulator(options: ReconOptions = ReconOptions()) -> Triangulator:
    """The triangulation engine `options.engine` names, as a function of (cameras, pixels, weights).

    "mvtex": `mvtex.recon.geometry.triangulate_points` (vectorised DLT + options.refine_iterations
    Gauss-Newton steps). "pycolmap": `mvtex.formats.colmap.triangulate_tracks` (COLMAP's multi-view
    triangulation + points-only bundle adjustment; cameras without skew).
    """
    if options.engine == "pycolmap":
        from mvtex.formats.colmap import triangulate_tracks

        return triangulate_tracks
    return partial(triangulate_points, iterations=options.refine_iterations)


def triangulate_observations(cameras: Sequence[Camera], pixels: np.ndarray, weights: np.ndarray,
                             options: ReconOptions = ReconOptions(), triangulate: Triangulator | None = None
                             ) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """Step 3: triangulate every point observed ≥ 2 times, robustly.

    While a point's worst observation exceeds options.max_reprojection_px and ≥ 3 remain,
    that observation is dropped and the point triangulated again.

    Args:
        cameras: the C cameras.
        pixels: (N,C,2) OpenCV pixels; weights: (N,C) 0/1 (from `resolve_ambiguity`).
        options: max_reprojection_px (and the engine's options).
        triangulate: the engine (default: `track_triangulator(options)`).

    Returns:
        points (N,3) float64 (NaN where fewer than 2 observations or degenerate), the
        weights (N,C) with dropped observations set to 0, and counts {"outlier_observations"}.
    """
    triangulate = track_triangulator(options) if triangulate is None else triangulate
    sizes = check_shape(pixels, "pixels", ("N", len(cameras), 2))
    check_shape(weights, "weights", ("N", len(cameras)), sizes)
    weights = np.array(weights, dtype=np.float64)
    counts = {"outlier_observations": 0}
    rows = np.flatnonzero(weights.sum(axis=1) >= 2)
    X = np.full((len(pixels), 3), np.nan)
    if not len(rows):
        return X, weights, counts
    X[rows] = triangulate(cameras, pixels[rows], weights[rows])
    todo = rows
    for _ in range(len(cameras)):
        err = reprojection_errors(cameras, X[todo], pixels[todo])
        err = np.where(weights[todo] > 0, np.nan_to_num(err, nan=np.inf), -1.0)
        worst = np.argmax(err, axis=1)
        bad = (err[np.arange(len(todo)), worst] > options.max_reprojection_px) & (weights[todo].sum(axis=1) >= 3)
        if not bad.any():
            break
        todo = todo[bad]
        weights[todo, worst[bad]] = 0.0
        counts["outlier_observations"] += int(bad.sum())
        X[todo] = triangulate(cameras, pixels[todo], weights[todo])
    return X, weights, counts


def accept_points(cameras: Sequence[Camera], points: np.ndarray, pixels: np.ndarray, weights: np.ndarray,
                  inferred_positions: np.ndarray, faces: np.ndarray, options: ReconOptions = ReconOptions()
                  ) -> tuple[np.ndarray, dict[str, int]]:
    """Step 4: which triangulated points to keep.

    A point observed by ≥ 2 cameras is rejected, in this order, if it is not finite or
    behind an observing camera ("cheirality"), if an observation's reprojection error
    exceeds options.max_reprojection_px ("reprojection"), or if it is farther than
    options.max_surface_distance_m from the inferred surface ("surface_distance").

    Args:
        cameras: the C cameras.
        points: (N,3) from `triangulate_observations`; pixels (N,C,2); weights (N,C).
        inferred_positions: (n',3) X_N; faces: (m',3) the inferred mesh.

    Returns:
        accepted (N,) bool, and rejected: reason -> count ("fewer_than_2_views",
        "reprojection", "surface_distance", "cheirality").
    """
    rows = np.flatnonzero(np.asarray(weights).sum(axis=1) >= 2)
    rejected = {"fewer_than_2_views": int(len(points) - len(rows)), "reprojection": 0, "surface_distance": 0,
                "cheirality": 0}
    accepted = np.zeros(len(points), bool)
    if not len(rows):
        return accepted, rejected
    X, w = points[rows], weights[rows]
    finite = np.all(np.isfinite(X), axis=1)
    _, y = project_points(cameras, np.nan_to_num(X))
    in_front = finite & np.all((y[..., 2] > 0) | (w == 0), axis=1)
    rejected["cheirality"] = int((~in_front).sum())
    err = reprojection_errors(cameras, np.nan_to_num(X), pixels[rows])
    err = np.where(w > 0, np.nan_to_num(err, nan=np.inf), 0.0).max(axis=1)
    reproj_ok = in_front & (err <= options.max_reprojection_px)
    rejected["reprojection"] = int((in_front & ~reproj_ok).sum())
    dist = np.full(len(rows), np.inf)
    dist[reproj_ok] = surface_distance(X[reproj_ok], inferred_positions, faces)
    near = reproj_ok & (dist <= options.max_surface_distance_m)
    rejected["surface_distance"] = int((reproj_ok & ~near).sum())
    accepted[rows[near]] = True
    return accepted, rejected


def pool_and_fill(points: np.ndarray, triangulated: np.ndarray, inferred: np.ndarray, faces: np.ndarray,
                  options: ReconOptions = ReconOptions()) -> tuple[np.ndarray, np.ndarray | None, dict[str, int]]:
    """Step 5: displacement on every gt vertex from the triangulated ones.

    Seam copies (split vertices at one position) are one physical point: their
    displacements are averaged and every copy gets it. The displacement is then extended
    harmonically to the vertices without one (`extrapolate.fill`, welded across seams)
    and, with options.smooth, Taubin-smoothed.

    Args:
        points: (n,3) triangulated positions (read where `triangulated`).
        triangulated: (n,) bool.
        inferred: (n,3) X_N of the gt vertices; faces: (m,3) the gt mesh.
        options: smooth, smooth_iterations.

    Returns:
        positions (n,3) float64, the positions before smoothing (None when not smoothed),
        and counts {"seam_copies_pooled"}.
    """
    n = len(inferred)
    groups = weld_groups(inferred)
    disp = np.zeros((n, 3))
    disp[triangulated] = points[triangulated] - inferred[triangulated]
    sums = np.zeros((n, 3))
    cnt = np.zeros(n)
    np.add.at(sums, groups[triangulated], disp[triangulated])
    np.add.at(cnt, groups[triangulated], 1.0)
    known = cnt[groups] > 0
    disp[known] = sums[groups[known]] / cnt[groups[known], None]
    counts = {"seam_copies_pooled": int((known & ~triangulated).sum())}

    disp = _fill(faces, inferred, disp, known, groups)
    out = inferred + disp
    unsmoothed = None
    if options.smooth:
        unsmoothed = out
        out = inferred + taubin_smooth(disp, welded_adjacency(faces, groups), options.smooth_iterations)
    return out, unsmoothed, counts


def _fill(faces: np.ndarray, positions: np.ndarray, values: np.ndarray, assigned: np.ndarray,
          groups: np.ndarray) -> np.ndarray:
    if not assigned.any():
        return np.zeros_like(values)
    if assigned.all():
        return values.copy()
    from mvtex.sliding.fill import fill

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


def reconstruct(gt_uv: np.ndarray, inferred_positions: np.ndarray, faces: np.ndarray, uv: np.ndarray,
                texcoords: dict[str, np.ndarray], rig: Rig, options: ReconOptions = ReconOptions(), *,
                gt_faces: np.ndarray | None = None, assigned: dict[str, np.ndarray] | None = None,
                progress: bool = False, ctx: GLContext | None = None) -> Reconstruction:
    """Triangulate the gt vertices from per-camera texture coordinates of an inferred mesh.

    Runs steps 1-5 of the module docstring.

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
        ctx: the GL context (`mvtex.render.context.GLContext`); one is made when None.

    Returns:
        Reconstruction on the n gt vertices.

    Raises:
        ValueError: shapes that do not fit, or fewer than 2 cameras.
    """
    gt_uv = np.asarray(gt_uv, dtype=np.float64)
    X_N = np.asarray(inferred_positions, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    sizes = check_shape(gt_uv, "gt_uv", ("n", 2))
    check_shape(X_N, "inferred_positions", ("n'", 3), sizes)
    check_shape(uv, "uv", ("n'", 2), sizes)
    check_shape(faces, "faces", ("m'", 3), sizes)
    n = len(gt_uv)
    if len(X_N) < n:
        raise ValueError(f"inferred_positions has {len(X_N)} vertices, fewer than the gt mesh's {n}")
    if gt_faces is None:
        if len(X_N) != n:
            raise ValueError("gt_faces is needed when the texcoord mesh is subdivided (n' > n)")
        gt_faces = faces
    gt_faces = np.asarray(gt_faces, dtype=np.int64)
    check_shape(gt_faces, "gt_faces", ("m", 3))
    names = [c for c in rig.names if c in texcoords]
    if len(names) < 2:
        raise ValueError(f"reconstruction needs texcoords of ≥ 2 rig cameras, got {sorted(texcoords)}")
    cameras = [rig[c] for c in names]
    triangulate = track_triangulator(options)

    hypotheses, stats = collect_hypotheses(gt_uv, X_N, faces, texcoords, cameras, uv_resolution=options.uv_resolution,
                                           depth_tolerance=options.depth_tolerance, assigned=assigned,
                                           require_assigned=options.require_assigned, progress=progress, ctx=ctx)
    pixels, weights, counts = resolve_ambiguity(hypotheses, n, cameras, options, triangulate)
    stats.update(counts)
    X, weights, counts = triangulate_observations(cameras, pixels, weights, options, triangulate)
    stats.update(counts)
    triangulated, rejected = accept_points(cameras, X, pixels, weights, X_N, faces, options)
    base = X_N[:n]
    points, unsmoothed, counts = pool_and_fill(X, triangulated, base, gt_faces, options)
    stats.update(counts)

    observed = (weights > 0) & triangulated[:, None]
    obs = {name: np.where(observed[:, [c]], pixels[:, c], np.nan) for c, name in enumerate(names)}
    err = reprojection_errors(cameras, points, np.stack([obs[name] for name in names], axis=1))
    used = np.isfinite(err)
    with np.errstate(invalid="ignore"):
        per_vertex = np.where(triangulated, np.nansum(err, axis=1) / np.maximum(used.sum(axis=1), 1), np.nan)
    return Reconstruction(points=points, inferred=base, triangulated=triangulated, observations=obs,
                          reprojection_error=per_vertex, rejected=rejected, stats=stats, unsmoothed=unsmoothed)
