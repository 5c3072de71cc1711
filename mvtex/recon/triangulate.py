"""Multi-view 3-D reconstruction from a texcoord set (DESIGN §5 "Reconstruction").

Every gt vertex i carries its material coordinate T_G[i]. Camera p sees the inferred mesh
with texture coordinates T_N^p; the pixel where p shows material T_G[i] is therefore the
projection of the inferred-surface point whose T_N^p equals T_G[i]. `reconstruct` runs
these steps, each a function of its own:

1. `mvtex.recon.locate.collect_hypotheses`: per camera, *locate* T_G[i] in the UV image of the
   inferred mesh (`locate_uv`: every triangle whose T_N^p contains it is a hypothesis,
   texcoords may fold over); the same barycentric combination of the inferred positions
   X_N is a 3-D point, kept where camera p sees it (depth test against a raster of the
   inferred mesh; the wearer's body, when there is one, hides it where the ray from the
   camera meets the body before it, by an exact ray cast); its projection is the
   observation.
2. `mvtex.recon.consensus.screen_hypotheses`: the triangle test drops hypotheses located in
   a triangle whose T_N is stretched across a fold edge (`ReconOptions.max_stretch`).
3. `mvtex.recon.consensus.vote`: per vertex, the hypotheses the cameras agree on (RANSAC over
   pairs of cameras, MSAC score, threshold `consensus_threshold`); this also chooses among
   several hypotheses of one camera.
4. `triangulate_observations`: every vertex with ≥ 2 agreeing observations is triangulated
   (the engine: `mvtex.recon.geometry.triangulate_points`, DLT + Gauss-Newton, or COLMAP
   through `mvtex.formats.colmap.triangulate_tracks`), dropping its worst observation while it
   exceeds options.max_reprojection_px.
5. `accept_points`: reject points behind a camera, with implausible reprojection error or
   far from the inferred surface.
6. `pool_and_fill`: seam copies pool their displacement; vertices not triangulated get X_N
   plus a harmonic extension of it (on the rest shape, `mvtex.sliding.fill.fill`); optional
   Taubin smoothing.

Every located hypothesis is either used or counted once by the reason it was left out
(`Reconstruction.rejected_observations`, `mvtex.recon.consensus.OBSERVATION_REASONS`).
Step 1 is the only one that rasterizes (GL, in `mvtex.recon.locate`); the geometry of the
others is `mvtex.recon.geometry` (NumPy).
`triangulate_pose` is the `mvtex triangulate` command for one dataset pose; writing its
output directory is `mvtex.recon.export`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import partial
from typing import TYPE_CHECKING, Any, Callable, Sequence

import numpy as np
import scipy.sparse as sp

from mvtex.data.camera import Camera
from mvtex.data.mesh import weld_groups, welded_adjacency
from mvtex.data.rig import Rig, as_rig
from mvtex.formats.colmap import triangulate_tracks
from mvtex.recon.consensus import HypothesisLedger, Vote, screen_hypotheses, vote
from mvtex.recon.geometry import (
    MIN_TRIANGULATION_ANGLE_DEG,
    observed,
    project_points,
    reprojection_errors,
    surface_distance,
    triangulate_points,
    triangulation_angles,
)
from mvtex.recon.locate import Hypotheses, collect_hypotheses
from mvtex.recon.options import ReconOptions, check_observation_count
from mvtex.recon.trust import (
    CONSISTENCY_INFLATION,
    consistency_sigma_px,
    fusion_factors,
    observation_sigma_px,
    point_sigma,
    trust_factors,
)
from mvtex.render.raster import check_mesh
from mvtex.sliding.fill import fill
from mvtex.util.checks import as_array, check_instance, check_shape
from mvtex.util.errors import OptionError

if TYPE_CHECKING:
    from mvtex.render.context import GLContext

# ReconOptions lives in mvtex.recon.options, the trust in mvtex.recon.trust; importing them
# from here keeps working.
__all__ = ["ReconOptions", "Reconstruction", "Triangulator", "accept_points", "consensus_threshold",
           "consistency_sigma_px", "point_sigma", "pool_and_fill", "reconstruct", "reconstruct_from_hypotheses",
           "taubin_smooth", "track_triangulator", "triangulate_observations", "trust_factors"]

# A triangulation engine: (cameras, pixels (N,C,2), weights (N,C)) -> points (N,3), NaN where degenerate.
Triangulator = Callable[[Sequence[Camera], np.ndarray, np.ndarray], np.ndarray]


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
        rejected: reason -> number of vertices not triangulated for it (`accept_points`).
        rejected_observations: reason -> number of located hypotheses not used for it
            (`mvtex.recon.consensus.OBSERVATION_REASONS`); with the used ones they add up to
            stats["hypotheses"].
        stats: counts of the stages, the vote's threshold ("consensus_threshold_px") and
            the number of observations used ("used_observations").
        unsmoothed: (n,3) float64 points before smoothing, or None when not smoothed.
        sigma: (n,) float64 the standard deviation (m) of each triangulated point that the
            texcoords' predictive uncertainty implies (`point_sigma`), NaN where not
            triangulated; None when the texcoords report no uncertainty.
    """

    points: np.ndarray
    inferred: np.ndarray
    triangulated: np.ndarray
    observations: dict[str, np.ndarray]
    reprojection_error: np.ndarray
    rejected: dict[str, int]
    rejected_observations: dict[str, int] = field(default_factory=dict)
    stats: dict[str, Any] = field(default_factory=dict)
    unsmoothed: np.ndarray | None = None
    sigma: np.ndarray | None = None

    @property
    def num_views(self) -> np.ndarray:
        """(n,) int number of cameras used per vertex."""
        return np.sum([np.isfinite(o[:, 0]) for o in self.observations.values()], axis=0).astype(np.int64)

    @property
    def displacement(self) -> np.ndarray:
        """(n,3) float64 points - inferred."""
        return self.points - self.inferred


def consensus_threshold(hypotheses: Hypotheses, num_vertices: int, cameras: Sequence[Camera],
                        options: ReconOptions = ReconOptions()) -> float:
    """The vote's inlier threshold (px) for one pose.

    options.consensus_px, grown to options.consensus_scale times the median reprojection
    error of a loose vote (threshold options.max_reprojection_px) where that is larger:
    texcoords with noise (predicted ones) then keep their observations, exact ones (TS)
    keep the tight threshold.
    """
    if not options.consensus_scale:  # None (no source to decide by) or 0
        return float(options.consensus_px)
    loose = vote(hypotheses, num_vertices, cameras, max(options.max_reprojection_px, options.consensus_px),
                 options.max_combinations, options.refine_iterations)
    ok = np.all(np.isfinite(loose.points), axis=1)
    if not ok.any():
        return float(options.consensus_px)
    err = reprojection_errors(cameras, loose.points[ok], loose.pixels[ok])[loose.weights[ok] > 0]
    return float(max(options.consensus_px, options.consensus_scale * np.median(err)))


def track_triangulator(options: ReconOptions = ReconOptions()) -> Triangulator:
    """The triangulation engine `options.engine` names, as a function of (cameras, pixels, weights).

    "mvtex": `mvtex.recon.geometry.triangulate_points` (vectorised DLT + options.refine_iterations
    Gauss-Newton steps). "pycolmap": `mvtex.formats.colmap.triangulate_tracks` (COLMAP's multi-view
    triangulation + points-only bundle adjustment; cameras without skew).
    """
    if options.engine == "pycolmap":

        return triangulate_tracks
    return partial(triangulate_points, iterations=options.refine_iterations)


def triangulate_observations(cameras: Sequence[Camera], pixels: np.ndarray, weights: np.ndarray,
                             options: ReconOptions = ReconOptions(), triangulate: Triangulator | None = None,
                             scale: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """Step 3: triangulate every point observed ≥ 2 times, robustly.

    While a point's worst observation exceeds options.max_reprojection_px and ≥ 3 remain,
    that observation is dropped and the point triangulated again. Observations with a
    non-finite pixel do not count, and a point whose rays meet within
    `mvtex.recon.geometry.MIN_TRIANGULATION_ANGLE_DEG` is NaN, whichever the engine.

    Args:
        cameras: the C cameras.
        pixels: (N,C,2) OpenCV pixels; weights: (N,C) 0/1 (from `mvtex.recon.consensus.vote`).
        options: max_reprojection_px (and the engine's options).
        triangulate: the engine (default: `track_triangulator(options)`).
        scale: optional (N,C) positive factors of the observations' weights in the
            least squares (1 / their standard deviation); which are used is `weights`'.

    Returns:
        points (N,3) float64 (NaN where fewer than 2 observations or degenerate), the
        weights (N,C) with dropped observations set to 0, and counts {"outlier_observations"}.
    """
    engine = track_triangulator(options) if triangulate is None else triangulate

    def triangulate(cameras, pixels, weights):  # no engine returns a point of too narrow rays
        X = np.array(engine(cameras, pixels, weights), dtype=np.float64)
        X[~(triangulation_angles(cameras, X, weights) >= MIN_TRIANGULATION_ANGLE_DEG)] = np.nan
        return X

    sizes = check_shape(pixels, "pixels", ("N", len(cameras), 2))
    check_shape(weights, "weights", ("N", len(cameras)), sizes)
    weights = observed(pixels, weights)
    counts = {"outlier_observations": 0}
    rows = np.flatnonzero(weights.sum(axis=1) >= 2)
    X = np.full((len(pixels), 3), np.nan)
    if not len(rows):
        return X, weights, counts
    scale = np.ones_like(weights) if scale is None else np.asarray(scale, dtype=np.float64)
    X[rows] = triangulate(cameras, pixels[rows], weights[rows] * scale[rows])
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
        X[todo] = triangulate(cameras, pixels[todo], weights[todo] * scale[todo])
    return X, weights, counts


def accept_points(cameras: Sequence[Camera], points: np.ndarray, pixels: np.ndarray, weights: np.ndarray,
                  inferred_positions: np.ndarray, faces: np.ndarray, options: ReconOptions = ReconOptions(),
                  voting: np.ndarray | None = None) -> tuple[np.ndarray, dict[str, int]]:
    """Step 5: which triangulated points to keep.

    A point observed by ≥ 2 cameras is rejected, in this order, if it is not finite or
    behind an observing camera ("cheirality"), if an observation's reprojection error
    exceeds options.max_reprojection_px ("reprojection"), or if it is farther than
    options.max_surface_distance from the inferred surface ("surface_distance").
    Vertices with fewer than 2 observations are "disagreement" where they had
    hypotheses in ≥ 2 cameras (`voting`) and "fewer_than_2_views" elsewhere.

    Args:
        cameras: the C cameras.
        points: (N,3) from `triangulate_observations`; pixels (N,C,2); weights (N,C).
        inferred_positions: (n',3) X_N; faces: (m',3) the inferred mesh.
        options: max_reprojection_px, max_surface_distance.
        voting: (N,) bool vertices with hypotheses in ≥ 2 cameras (None: none).

    Returns:
        accepted (N,) bool, and rejected: reason -> count ("fewer_than_2_views",
        "disagreement", "cheirality", "reprojection", "surface_distance").
    """
    rows = np.flatnonzero(np.asarray(weights).sum(axis=1) >= 2)
    lacking = np.ones(len(points), bool)
    lacking[rows] = False
    disagree = int((lacking & voting).sum()) if voting is not None else 0
    rejected = {"fewer_than_2_views": int(lacking.sum()) - disagree, "disagreement": disagree, "cheirality": 0,
                "reprojection": 0, "surface_distance": 0}
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
    near = reproj_ok & (dist <= options.max_surface_distance)
    rejected["surface_distance"] = int((reproj_ok & ~near).sum())
    accepted[rows[near]] = True
    return accepted, rejected


def pool_and_fill(points: np.ndarray, triangulated: np.ndarray, inferred: np.ndarray, faces: np.ndarray,
                  options: ReconOptions = ReconOptions(), rest: np.ndarray | None = None,
                  trust: np.ndarray | None = None, extend: bool = True
                  ) -> tuple[np.ndarray, np.ndarray | None, dict[str, int]]:
    """Step 6: displacement on every gt vertex from the triangulated ones.

    Seam copies (split vertices at one position) are one physical point: their
    displacements are averaged and every copy gets it. The displacement is then extended
    harmonically to the vertices without one (`mvtex.sliding.fill.fill`, welded across
    seams, cotangent weights of `rest` when options.fill_shape is "rest" and a rest shape
    is given, else of `inferred`) and, with options.smooth, Taubin-smoothed.

    Args:
        points: (n,3) triangulated positions (read where `triangulated`).
        triangulated: (n,) bool.
        inferred: (n,3) X_N of the gt vertices; faces: (m,3) the gt mesh.
        options: fill_shape, smooth, smooth_iterations.
        rest: (n,3) the rest shape, or None.
        trust: optional (n,) factors in [0,1] of the triangulated displacements
            (`trust_factors`): a vertex of factor 0 keeps its inferred position, and is a
            fixed zero of the extension, so it passes no displacement on either.
        extend: extend the displacement to the vertices without one; False: they keep
            their `inferred` position (a prior that stands where no camera triangulates).

    Returns:
        positions (n,3) float64, the positions before smoothing (None when not smoothed),
        and counts {"seam_copies_pooled"}.
    """
    n = len(inferred)
    groups = weld_groups(inferred)
    disp = np.zeros((n, 3))
    disp[triangulated] = points[triangulated] - inferred[triangulated]
    if trust is not None:
        disp *= np.asarray(trust, dtype=np.float64)[:, None]
    sums = np.zeros((n, 3))
    cnt = np.zeros(n)
    np.add.at(sums, groups[triangulated], disp[triangulated])
    np.add.at(cnt, groups[triangulated], 1.0)
    known = cnt[groups] > 0
    disp[known] = sums[groups[known]] / cnt[groups[known], None]
    counts = {"seam_copies_pooled": int((known & ~triangulated).sum())}

    shape = inferred
    if options.fill_shape == "rest" and rest is not None:
        shape = np.asarray(rest, dtype=np.float64)
        check_shape(shape, "rest", (n, 3))
    if extend:
        disp = _fill(faces, shape, disp, known, groups)
    else:
        disp[~known] = 0.0
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
                rest: np.ndarray | None = None, body: tuple[np.ndarray, np.ndarray] | None = None,
                uncertainty: dict[str, np.ndarray] | None = None, prior_sigma: np.ndarray | None = None,
                progress: bool = False, ctx: GLContext | None = None) -> Reconstruction:
    """Triangulate the gt vertices from per-camera texture coordinates of an inferred mesh.

    Runs steps 1-6 of the module docstring.

    Args:
        gt_uv: (n,2) T_G of the gt mesh's vertices.
        inferred_positions: (n',3) X_N on the texcoord set's (possibly subdivided) mesh; its
            first n vertices are the gt mesh's vertices (DESIGN §4 `parent`).
        faces: (m',3) int faces of the texcoord set's mesh.
        uv: (n',2) T_G on the texcoord set's mesh (the triangle test compares T_N with it).
        texcoords: camera name -> (n',2) T_N of that camera; ≥ 2 cameras of `rig`.
        rig: the cameras (those named in `texcoords` are used).
        options: see ReconOptions.
        gt_faces: (m,3) faces of the gt mesh (needed to fill and smooth when n' > n;
            defaults to `faces` when n' == n).
        assigned: optional camera name -> (n',) bool (used with options.require_assigned).
        rest: optional (n,3) rest shape of the gt mesh (the fill's shape, options.fill_shape).
        body: optional (positions (nb,3), faces (mb,3)) of the wearer's body in this pose: no
            observation it hides from a camera is used.
        uncertainty: optional camera name -> (n',) predictive standard deviation of that
            camera's T_N (uv units; `mvtex.data.texcoords.TexcoordSet.uncertainty`), for
            every camera or none: observations are weighted by it and points trusted by it
            (options.use_uncertainty).
        prior_sigma: optional (n,) standard deviation (m) of `inferred_positions` as a
            prior (a corrected set's `geometry_uncertainty`): each point is fused with it
            (`mvtex.recon.trust.fusion_factors`); with options.prior_fill (the default)
            the fused displacement is extended to the vertices no camera triangulates,
            without it they keep the prior.
        progress: show a progress bar over cameras.
        ctx: the GL context (`mvtex.render.context.GLContext`); one is made when None.

    Returns:
        Reconstruction on the n gt vertices.

    Raises:
        ValueError: shapes that do not fit, or fewer than 2 cameras.
    """

    check_instance(options, ReconOptions, "options")
    rig = as_rig(rig)
    gt_uv = as_array(gt_uv, "gt_uv")
    X_N, faces = check_mesh(inferred_positions, faces, "inferred_positions", size="n'", faces_size="m'")
    faces = faces.astype(np.int64)
    uv = as_array(uv, "uv")
    if not isinstance(texcoords, dict) or not all(isinstance(k, str) for k in texcoords):
        raise OptionError("texcoords", "must be a dict: camera name -> (n',2) T_N")
    texcoords = {c: as_array(t, f"texcoords[{c!r}]") for c, t in texcoords.items()}
    for c, t in texcoords.items():
        check_shape(t, f"texcoords[{c!r}]", (len(X_N), 2))
        if not np.all(np.isfinite(t)):
            raise OptionError(None, f"texcoords[{c!r}] has NaN or infinite values")
    if gt_faces is not None:
        gt_faces = as_array(gt_faces, "gt_faces", np.int64)
    if rest is not None:
        rest = as_array(rest, "rest")
    sizes = check_shape(gt_uv, "gt_uv", ("n", 2))
    check_shape(X_N, "inferred_positions", ("n'", 3), sizes)
    check_shape(uv, "uv", ("n'", 2), sizes)
    check_shape(faces, "faces", ("m'", 3), sizes)
    n = len(gt_uv)
    if len(X_N) < n:
        raise OptionError("inferred_positions", f"has {len(X_N)} vertices, fewer than the gt mesh's {n}")
    if gt_faces is None:
        if len(X_N) != n:
            raise OptionError("gt_faces", "is needed when the texcoord mesh is subdivided (n' > n)")
        gt_faces = faces
    gt_faces = np.asarray(gt_faces, dtype=np.int64)
    check_shape(gt_faces, "gt_faces", ("m", 3))
    if gt_faces.size and (gt_faces.min() < 0 or gt_faces.max() >= n):
        raise OptionError("gt_faces", f"must index the {n} gt vertices")
    if assigned is not None and (not isinstance(assigned, dict) or not all(
            isinstance(a, np.ndarray) and a.dtype == np.bool_ and a.shape == (len(X_N),) for a in assigned.values())):
        raise OptionError("assigned", f"must be a dict: camera name -> ({len(X_N)},) bool array")
    if body is not None:
        if not isinstance(body, (tuple, list)) or len(body) != 2:
            raise OptionError("body", "must be (positions (nb,3), faces (mb,3))")
        body = check_mesh(body[0], body[1], "body positions")
    if rest is not None:
        check_shape(rest, "rest", (n, 3))
    if prior_sigma is not None:
        prior_sigma = as_array(prior_sigma, "prior_sigma")
        check_shape(prior_sigma, "prior_sigma", (n,))
        if not np.all(np.isfinite(prior_sigma) & (prior_sigma >= 0)):
            raise OptionError("prior_sigma", "must be finite and non-negative")
    names = [c for c in rig.names if c in texcoords]
    if len(names) < 2:
        raise OptionError("texcoords", f"must hold texcoords of ≥ 2 rig cameras for a reconstruction, got "
                          f"{sorted(texcoords)}")
    check_observation_count(n, len(names))
    cameras = [rig[c] for c in names]
    hypotheses, stats = collect_hypotheses(gt_uv, X_N, faces, texcoords, cameras, uv_resolution=options.uv_resolution,
                                           depth_tolerance=options.depth_tolerance, assigned=assigned,
                                           require_assigned=options.require_assigned, body=body,
                                           uncertainty=uncertainty if options.use_uncertainty else None,
                                           progress=progress, ctx=ctx)
    return reconstruct_from_hypotheses(hypotheses, stats, n, X_N, faces, uv, {c: texcoords[c] for c in names},
                                       rig.select(names), options, gt_faces=gt_faces, rest=rest,
                                       prior_sigma=prior_sigma)


def reconstruct_from_hypotheses(hypotheses: Hypotheses, stats: dict[str, int], num_vertices: int,
                                inferred_positions: np.ndarray, faces: np.ndarray, uv: np.ndarray,
                                texcoords: dict[str, np.ndarray], rig: Rig, options: ReconOptions = ReconOptions(),
                                *, gt_faces: np.ndarray, rest: np.ndarray | None = None,
                                prior_sigma: np.ndarray | None = None) -> Reconstruction:
    """Steps 2-6 of the module docstring from the located hypotheses (no GL).

    Args:
        hypotheses, stats: from `collect_hypotheses` with the cameras of `rig` in its order.
        num_vertices: n, the number of gt vertices.
        inferred_positions, faces, uv, texcoords, options, rest, prior_sigma: as `reconstruct`.
        rig: the cameras, one per texcoords entry, in the hypotheses' camera order.
        gt_faces: (m,3) faces of the gt mesh (its n vertices are the first n of the
            texcoord set's mesh).

    Returns:
        Reconstruction on the n gt vertices.
    """
    X_N = np.asarray(inferred_positions, dtype=np.float64)
    gt_faces = np.asarray(gt_faces, dtype=np.int64)
    n = int(num_vertices)
    names = list(rig.names)
    cameras = list(rig)
    stats = dict(stats)
    triangulate = track_triangulator(options)
    ledger = HypothesisLedger()
    for reason in ("unassigned", "duplicate", "occluded", "hidden_by_body"):
        ledger.add(reason, stats.get(reason, 0))
    hypotheses, stretched = screen_hypotheses(hypotheses, faces, uv, [np.asarray(texcoords[c]) for c in names],
                                              options.max_stretch)
    ledger.add("stretched_triangle", stretched)
    threshold = consensus_threshold(hypotheses, n, cameras, options)
    voted: Vote = vote(hypotheses, n, cameras, threshold, options.max_combinations, options.refine_iterations)
    for reason in ("fewer_than_2_views", "alternative", "disagreement"):
        ledger.add(reason, voted.counts[reason])
    stats.update(ambiguous_vertices=voted.counts["ambiguous_vertices"], consensus_threshold_px=threshold)
    pixels = voted.pixels
    sigma_px = observation_sigma_px(hypotheses, pixels, voted.points, cameras) if options.use_uncertainty else None
    scale = None
    if sigma_px is not None:  # weights 1/σ, relative to the vertex's best observation
        with np.errstate(divide="ignore", invalid="ignore"):
            inverse = np.where(np.isfinite(sigma_px) & (sigma_px > 0), 1.0 / sigma_px, 0.0)
            scale = np.where(voted.weights > 0, inverse / np.maximum(inverse.max(axis=1, keepdims=True), 1e-300), 1.0)
        scale = np.where(scale > 0, scale, 1e-6)
    X, weights, counts = triangulate_observations(cameras, pixels, voted.weights, options, triangulate, scale)
    ledger.add("reprojection", counts["outlier_observations"])
    views = np.zeros((n, len(cameras)), bool)
    views[hypotheses.vertex, hypotheses.camera] = True
    triangulated, rejected = accept_points(cameras, X, pixels, weights, X_N, faces, options,
                                           voting=views.sum(axis=1) >= 2)
    observed = (weights > 0) & triangulated[:, None]
    ledger.add("point_rejected", int((weights > 0).sum() - observed.sum()))
    stats["used_observations"] = int(observed.sum())
    base = X_N[:n]
    sigma, trust = None, None
    if options.shrink and sigma_px is None:  # no reported uncertainty: the cameras' disagreement
        pooled = consistency_sigma_px(cameras, X, pixels, weights * triangulated[:, None])
        stats["consistency_sigma_px"] = pooled
        sigma_px = np.where(weights > 0, CONSISTENCY_INFLATION * pooled if math.isfinite(pooled) else np.inf, np.inf)
    if sigma_px is not None:
        sigma = np.full(n, np.nan)
        sigma[triangulated] = point_sigma(cameras, X[triangulated], weights[triangulated], sigma_px[triangulated])
    fused = prior_sigma is not None and options.use_prior
    if fused:
        trust = np.zeros(n)
        trust[triangulated], outlier = fusion_factors(
            X[triangulated] - base[triangulated], None if sigma is None else sigma[triangulated],
            np.asarray(prior_sigma, np.float64)[triangulated], options.shrink or 0.0, options.prior_gate,
            options.max_surface_distance)
        stats.update(prior_outliers=int(outlier.sum()),
                     mean_trust=float(trust[triangulated].mean()) if triangulated.any() else 0.0)
    elif options.shrink:
        trust = np.zeros(n)
        trust[triangulated] = trust_factors(X[triangulated] - base[triangulated], sigma[triangulated], options.shrink,
                                            options.max_surface_distance)
        stats["mean_trust"] = float(trust[triangulated].mean()) if triangulated.any() else 0.0
    points, unsmoothed, counts = pool_and_fill(X, triangulated, base, gt_faces, options, rest, trust,
                                               extend=not fused or options.prior_fill)
    stats.update(counts)

    obs = {name: np.where(observed[:, [c]], pixels[:, c], np.nan) for c, name in enumerate(names)}
    err = reprojection_errors(cameras, points, np.stack([obs[name] for name in names], axis=1))
    used = np.isfinite(err)
    with np.errstate(invalid="ignore"):
        per_vertex = np.where(triangulated, np.nansum(err, axis=1) / np.maximum(used.sum(axis=1), 1), np.nan)
    return Reconstruction(points=points, inferred=base, triangulated=triangulated, observations=obs,
                          reprojection_error=per_vertex, rejected=rejected,
                          rejected_observations=dict(ledger.rejected), stats=stats, unsmoothed=unsmoothed,
                          sigma=sigma)
