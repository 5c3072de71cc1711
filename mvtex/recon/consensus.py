"""Which located observations a reconstruction trusts: steps 2 and 3 of
`mvtex.recon.triangulate.reconstruct`.

A hypothesis (`mvtex.recon.locate.Hypotheses`) is wrong by millimeters where T_N
interpolates across a fold edge: the gt material jumps between two corners of the inferred
triangle it was located in, so the interpolated material inside it belongs to neither side.
Two independent rules catch such observations:

- `screen_hypotheses`, the triangle test (the edge test of the paper's Appendix A.1 applied
  at lookup time): an edge whose ‖ΔT_N‖ is much longer than its ‖ΔT_G‖ (`triangle_stretch`)
  joins material far apart on the cloth; hypotheses in such a triangle are dropped.
- `vote`, the cameras' agreement (RANSAC over the few cameras): per vertex, every pair of
  hypotheses from two cameras is triangulated; the pair whose point the vertex's other
  hypotheses agree with best (MSAC: least summed truncated squared reprojection error)
  wins, each camera keeps its hypothesis nearest to the point, and cameras farther than
  the threshold are left out. This also chooses among several hypotheses of one camera
  (fold-overs). With two cameras nothing can be voted out; the pair must still agree
  within the threshold.

Every hypothesis left out is counted by reason (`HypothesisLedger`), so a report accounts
for each located hypothesis.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from mvtex.data.camera import Camera
from mvtex.recon.geometry import camera_arrays, triangulate_points
from mvtex.recon.locate import Hypotheses

# Why a located hypothesis was not used, in the order the steps decide it.
OBSERVATION_REASONS = ("unassigned", "duplicate", "occluded", "hidden_by_body", "stretched_triangle",
                       "fewer_than_2_views", "alternative", "disagreement", "reprojection", "point_rejected")


@dataclass
class HypothesisLedger:
    """Counts of located hypotheses not used, by reason (`OBSERVATION_REASONS`).

    Attributes:
        rejected: reason -> number of hypotheses.
    """

    rejected: dict[str, int] = field(default_factory=lambda: dict.fromkeys(OBSERVATION_REASONS, 0))

    def add(self, reason: str, count: int) -> None:
        """Count `count` more hypotheses rejected for `reason`."""
        if reason not in self.rejected:
            raise ValueError(f"unknown observation reason {reason!r}")
        self.rejected[reason] += int(count)


def triangle_stretch(faces: np.ndarray, uv: np.ndarray, texcoords: np.ndarray, face: np.ndarray) -> np.ndarray:
    """The largest ratio ‖ΔT_N‖ / ‖ΔT_G‖ over the three edges of each given triangle.

    Within one UV chart T_G is proportional to the material, so a ratio well above 1
    means the edge's two T_N lie farther apart on the cloth than its ends do.

    Args:
        faces: (m,3) int triangles of the texcoord set's mesh.
        uv: (n,2) T_G on that mesh.
        texcoords: (n,2) T_N of one camera.
        face: (h,) int indices of the triangles to measure.

    Returns:
        (h,) float64 (inf where an edge has ‖ΔT_G‖ = 0).
    """
    f = np.asarray(faces, dtype=np.int64)[np.asarray(face, dtype=np.int64)]
    g = np.asarray(uv, dtype=np.float64)[f]
    t = np.asarray(texcoords, dtype=np.float64)[f]
    ratio = np.zeros(len(f))
    for a, b in ((0, 1), (1, 2), (2, 0)):
        dn = np.linalg.norm(t[:, a] - t[:, b], axis=1)
        dg = np.linalg.norm(g[:, a] - g[:, b], axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.maximum(ratio, np.where(dg > 0, dn / dg, np.inf))
    return ratio


def screen_hypotheses(hypotheses: Hypotheses, faces: np.ndarray, uv: np.ndarray,
                      texcoords: Sequence[np.ndarray], max_stretch: float | None) -> tuple[Hypotheses, int]:
    """The triangle test: drop hypotheses located in a triangle stretched beyond max_stretch.

    Args:
        hypotheses: from `collect_hypotheses`.
        faces: (m,3) and uv (n,2): the texcoord set's mesh and its T_G.
        texcoords: T_N (n,2) of each camera, in the hypotheses' camera order.
        max_stretch: see `ReconOptions.max_stretch`; None keeps every hypothesis.

    Returns:
        The kept hypotheses and the number dropped.
    """
    if max_stretch is None or not len(hypotheses.vertex):
        return hypotheses, 0
    keep = np.ones(len(hypotheses.vertex), bool)
    for c, T in enumerate(texcoords):
        rows = np.flatnonzero(hypotheses.camera == c)
        keep[rows] = triangle_stretch(faces, uv, T, hypotheses.face[rows]) <= max_stretch
    return hypotheses.subset(keep), int((~keep).sum())


def _pair_templates(m: int) -> np.ndarray:
    """(m(m-1)/2, 2) all index pairs i < j of range(m)."""
    i, j = np.triu_indices(m, k=1)
    return np.stack([i, j], axis=1)


def _pair_points(K: np.ndarray, R: np.ndarray, t: np.ndarray, ca: np.ndarray, xa: np.ndarray, cb: np.ndarray,
                 xb: np.ndarray) -> np.ndarray:
    """Two-view DLT (normalised coordinates) of pairs of pixels xa (p,2), xb (p,2) in cameras ca, cb (p,)."""
    P = np.concatenate([R, t[:, :, None]], axis=2)
    rows = []
    for c, x in ((ca, xa), (cb, xb)):
        k = K[c]
        yn = (x[:, 1] - k[:, 1, 2]) / k[:, 1, 1]
        xn = (x[:, 0] - k[:, 0, 2] - k[:, 0, 1] * yn) / k[:, 0, 0]
        rows += [xn[:, None] * P[c, 2] - P[c, 0], yn[:, None] * P[c, 2] - P[c, 1]]
    _, _, vt = np.linalg.svd(np.stack(rows, axis=1))
    X = vt[:, -1]
    with np.errstate(divide="ignore", invalid="ignore"):
        out = X[:, :3] / X[:, 3:4]
    out[~np.all(np.isfinite(out), axis=1)] = np.nan
    return out


def _project_indexed(K: np.ndarray, R: np.ndarray, t: np.ndarray, cam: np.ndarray, X: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Points X (h,3), each into its own camera cam (h,): pixels (h,2) and depth (h,)."""
    pix = np.empty((len(X), 2))
    z = np.empty(len(X))
    for c in np.unique(cam):
        rows = np.flatnonzero(cam == c)
        y = X[rows] @ R[c].T + t[c]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = y[:, 0] / y[:, 2]
            v = y[:, 1] / y[:, 2]
        pix[rows, 0] = K[c, 0, 0] * u + K[c, 0, 1] * v + K[c, 0, 2]
        pix[rows, 1] = K[c, 1, 1] * v + K[c, 1, 2]
        z[rows] = y[:, 2]
    return pix, z


@dataclass(frozen=True)
class Vote:
    """The outcome of `vote` for n vertices and C cameras.

    Attributes:
        pixels: (n,C,2) float64 the chosen observation per (vertex, camera), NaN where none.
        weights: (n,C) float64 1 where chosen, else 0.
        points: (n,3) float64 the consensus point (triangulated from the chosen
            observations), NaN where fewer than 2 agree.
        threshold_px: the inlier threshold used.
        counts: hypotheses left out by reason ("fewer_than_2_views", "alternative",
            "disagreement") and "ambiguous_vertices" (vertices with several hypotheses in a camera).
    """

    pixels: np.ndarray
    weights: np.ndarray
    points: np.ndarray
    threshold_px: float
    counts: dict[str, int]


def vote(hypotheses: Hypotheses, num_vertices: int, cameras: Sequence[Camera], threshold_px: float,
         max_pairs: int = 256, refine_iterations: int = 5, rounds: int = 2) -> Vote:
    """Step 3: per vertex, the observations the cameras agree on (module docstring).

    A vertex with one hypothesis per camera whose all-camera point reprojects within the
    threshold everywhere is taken as it is (the common case; RANSAC would find the same
    set). The others run the pairs: the best pair's point is refined on its inliers and
    the inliers chosen again, `rounds` times.

    Args:
        hypotheses: the screened hypotheses.
        num_vertices: n, the number of gt vertices.
        cameras: the C cameras.
        threshold_px: inlier threshold (px).
        max_pairs: at most this many hypothesis pairs per vertex (the first in camera order).
        refine_iterations: Gauss-Newton steps of the consensus points.
        rounds: re-selections of the inliers against the refined point (local optimisation).

    Returns:
        The `Vote`.
    """
    n, C = int(num_vertices), len(cameras)
    K, R, t = camera_arrays(cameras)
    tau2 = float(threshold_px) ** 2
    order = np.lexsort((hypotheses.camera, hypotheses.vertex))
    hv, hc, hpx = hypotheses.vertex[order], hypotheses.camera[order], hypotheses.pixel[order]
    counts = {"fewer_than_2_views": 0, "alternative": 0, "disagreement": 0, "ambiguous_vertices": 0}
    pixels = np.full((n, C, 2), np.nan)
    weights = np.zeros((n, C))
    points = np.full((n, 3), np.nan)
    out = Vote(pixels, weights, points, float(threshold_px), counts)
    if not len(hv):
        return out
    verts, start, size = np.unique(hv, return_index=True, return_counts=True)
    per_cam = np.zeros((n, C), np.int64)
    np.add.at(per_cam, (hv, hc), 1)
    views = (per_cam[verts] > 0).sum(axis=1)
    counts["ambiguous_vertices"] = int(np.sum(np.any(per_cam[verts] > 1, axis=1) & (views >= 2)))
    counts["fewer_than_2_views"] = int(size[views < 2].sum())
    slots = np.flatnonzero(views >= 2)  # index into verts
    if not len(slots):
        return out
    chosen = np.full((len(slots), C), -1, np.int64)  # per voting vertex and camera: a hypothesis
    point = np.full((len(slots), 3), np.nan)

    # The common case: one hypothesis per camera, all within the threshold of their point.
    slot_of = np.full(len(verts), -1, np.int64)
    slot_of[slots] = np.arange(len(slots))
    hslot = slot_of[np.repeat(np.arange(len(verts)), size)]
    voting_hyp = hslot >= 0
    single = np.all(per_cam[verts[slots]] <= 1, axis=1)
    everything = np.full((len(slots), C), -1, np.int64)
    everything[hslot[voting_hyp], hc[voting_hyp]] = np.flatnonzero(voting_hyp)
    fast = np.flatnonzero(single)
    if len(fast):
        X = _triangulate_chosen(cameras, everything[fast], hpx, refine_iterations)
        good = _all_within(K, R, t, X, everything[fast], hpx, tau2)
        chosen[fast[good]] = everything[fast[good]]
        point[fast[good]] = X[good]
    todo = np.flatnonzero(np.all(chosen == -1, axis=1))
    if len(todo):
        c_todo, x_todo = _ransac(cameras, K, R, t, slots[todo], start, size, hc, hpx, C, tau2, max_pairs,
                                 refine_iterations, rounds)
        chosen[todo], point[todo] = c_todo, x_todo

    agree = (chosen >= 0).sum(axis=1) >= 2
    v = verts[slots]
    rows, cams = np.nonzero((chosen >= 0) & agree[:, None])
    pixels[v[rows], cams] = hpx[chosen[rows, cams]]
    weights[v[rows], cams] = 1.0
    points[v[agree]] = point[agree]

    # The left-out hypotheses of voting vertices: another of the same camera was chosen
    # ("alternative"), or none of their camera agrees ("disagreement").
    cams_used = weights > 0
    in_used_camera = voting_hyp & cams_used[hv, hc]
    counts["alternative"] = int(in_used_camera.sum() - cams_used.sum())
    counts["disagreement"] = int((voting_hyp & ~cams_used[hv, hc]).sum())
    return out


def _triangulate_chosen(cameras: Sequence[Camera], chosen: np.ndarray, hpx: np.ndarray, iterations: int
                        ) -> np.ndarray:
    """Points (k,3) triangulated from the chosen hypotheses (k,C) (NaN where < 2 chosen)."""
    w = (chosen >= 0).astype(np.float64)
    px = np.where((chosen >= 0)[..., None], hpx[np.maximum(chosen, 0)], np.nan)
    X = np.full((len(chosen), 3), np.nan)
    enough = w.sum(axis=1) >= 2
    if enough.any():
        X[enough] = triangulate_points(cameras, px[enough], w[enough], iterations)
    return X


def _all_within(K, R, t, X, chosen, hpx, tau2) -> np.ndarray:
    """(k,) bool: X is finite and every chosen hypothesis is in front of its camera and
    within the threshold of X's projection."""
    ok = np.all(np.isfinite(X), axis=1)
    rows, cams = np.nonzero(chosen >= 0)
    proj, z = _project_indexed(K, R, t, cams, np.nan_to_num(X[rows]))
    far = ~((z > 0) & (np.sum((proj - hpx[chosen[rows, cams]]) ** 2, axis=1) <= tau2))
    ok[rows[far]] = False
    return ok


def _ransac(cameras, K, R, t, owner, start, size, hc, hpx, C, tau2, max_pairs, iterations, rounds
            ) -> tuple[np.ndarray, np.ndarray]:
    """The pairs vote of the vertices (slots into `start`/`size`) `owner` (k,): chosen
    hypotheses (k,C) int64 (-1: none) and their points (k,3)."""
    # Every hypothesis pair of two cameras of a vertex, vertices grouped by hypothesis count.
    pa, pb, ps = [], [], []
    local = np.arange(len(owner))
    for m in np.unique(size[owner]):
        rows = local[size[owner] == m]
        tmpl = _pair_templates(int(m))
        a = start[owner[rows]][:, None] + tmpl[None, :, 0]
        b = start[owner[rows]][:, None] + tmpl[None, :, 1]
        ok = hc[a] != hc[b]
        ok &= np.cumsum(ok, axis=1) <= max_pairs
        r, q = np.nonzero(ok)
        pa.append(a[r, q])
        pb.append(b[r, q])
        ps.append(rows[r])
    pa, pb, ps = np.concatenate(pa), np.concatenate(pb), np.concatenate(ps)
    X = _pair_points(K, R, t, hc[pa], hpx[pa], hc[pb], hpx[pb])
    _, za = _project_indexed(K, R, t, hc[pa], np.nan_to_num(X))
    _, zb = _project_indexed(K, R, t, hc[pb], np.nan_to_num(X))
    cost = _msac_cost(K, R, t, X, owner[ps], start, size, hc, hpx, C, tau2)
    cost = np.where(np.all(np.isfinite(X), axis=1) & (za > 0) & (zb > 0), cost, np.inf)
    best_order = np.lexsort((cost, ps))
    first = np.ones(len(best_order), bool)
    first[1:] = ps[best_order[1:]] != ps[best_order[:-1]]
    best = best_order[first]  # one per vertex, in local order
    current = np.where(np.isfinite(cost[best])[:, None], X[best], np.nan)

    # Local optimisation: inliers of the seed point, triangulated, inliers again.
    chosen = _nearest_inliers(K, R, t, current, owner, start, size, hc, hpx, C, tau2)
    for _ in range(max(1, int(rounds))):
        refined = _triangulate_chosen(cameras, chosen, hpx, iterations)
        current = np.where(np.isfinite(refined), refined, current)
        again = _nearest_inliers(K, R, t, current, owner, start, size, hc, hpx, C, tau2)
        changed = np.any(again != chosen, axis=1)
        chosen = again
        if not changed.any():
            break
    else:
        # The last selection changed: its point is triangulated from it.
        refined = _triangulate_chosen(cameras, chosen[changed], hpx, iterations)
        current[changed] = refined
    return chosen, current


def _msac_cost(K, R, t, X, owner, start, size, hc, hpx, C, tau2) -> np.ndarray:
    """Per point X[p] of vertex slot owner[p]: Σ over the vertex's cameras of the truncated
    squared distance min(r², τ²) of that camera's nearest hypothesis."""
    reps = size[owner]
    which = np.repeat(np.arange(len(X)), reps)
    offset = np.arange(len(which)) - np.repeat(np.cumsum(reps) - reps, reps)
    hyp = start[owner][which] + offset
    proj, z = _project_indexed(K, R, t, hc[hyp], np.nan_to_num(X[which]))
    r2 = np.where(z > 0, np.sum((proj - hpx[hyp]) ** 2, axis=1), np.inf)
    r2 = np.nan_to_num(r2, nan=np.inf)
    best = np.full((len(X), C), np.inf)
    np.minimum.at(best, (which, hc[hyp]), r2)
    present = np.zeros((len(X), C), bool)
    present[which, hc[hyp]] = True
    return np.where(present, np.minimum(best, tau2), 0.0).sum(axis=1)


def _nearest_inliers(K, R, t, X, owner, start, size, hc, hpx, C, tau2) -> np.ndarray:
    """(len(X), C) int64: per camera the hypothesis (sorted index) nearest to the projection
    of X[p] within the threshold, -1 where none."""
    reps = size[owner]
    which = np.repeat(np.arange(len(X)), reps)
    offset = np.arange(len(which)) - np.repeat(np.cumsum(reps) - reps, reps)
    hyp = start[owner][which] + offset
    proj, z = _project_indexed(K, R, t, hc[hyp], np.nan_to_num(X[which]))
    r2 = np.where((z > 0) & np.all(np.isfinite(X[which]), axis=1), np.sum((proj - hpx[hyp]) ** 2, axis=1), np.inf)
    r2 = np.nan_to_num(r2, nan=np.inf)
    # Within each (point, camera), nearest first.
    key = np.lexsort((r2, hc[hyp], which))
    w_s, c_s, r_s, h_s = which[key], hc[hyp][key], r2[key], hyp[key]
    head = np.ones(len(key), bool)
    head[1:] = (w_s[1:] != w_s[:-1]) | (c_s[1:] != c_s[:-1])
    head &= r_s <= tau2
    chosen = np.full((len(X), C), -1, np.int64)
    chosen[w_s[head], c_s[head]] = h_s[head]
    return chosen
