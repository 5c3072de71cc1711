"""Per-pixel texture-coordinate error (DESIGN §5 "Per-pixel error", the paper's SqrtMSE).

The ground-truth mesh is rendered with its uv (T_G) and the inferred mesh with the
texcoords under test from the same camera; over the pixels covered by both,
e = ‖uv_inferred − uv_gt‖ and an image's SqrtMSE = sqrt(mean e²). `evaluate` reports the
mean ± std over images for the baseline (inferred mesh with T_G) and for a texcoord set.

Where the two meshes show different UV charts at a pixel (a side seam near the silhouette,
the rim of an opening), e measures the distance between charts in the atlas, not between
material points: a handful of such pixels (e ≈ 0.5–1) can outweigh everything else. No
texcoords can remove them, since the charts' boundaries are fixed by each mesh's geometry.
`evaluate` therefore also reports `sqrt_mse_same_chart`: the same statistic over the pixels
where both meshes show the same chart (the contract keys are unchanged).

The *material error* needs no such exclusion: at a pixel, each mesh shows a point of the
garment's material — for gt the barycentric combination of the rest positions (mesh.npz
`rest`) of the triangle it shows, for the inferred mesh the point its texcoords name in the
uv layout, mapped back to the rest shape (`MaterialMap`). Their distance on the rest
garment, in meters, is small across a seam (both sides of it are neighbours on the
cloth). `evaluate` reports its RMSE per image as `material_rmse_m` (null without `rest`).
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from .camera import Camera, Rig
from .parallel import ThreadState

if TYPE_CHECKING:
    from .raster import GLContext, Raster

HEATMAP_MAX = 0.04
MATERIAL_HEATMAP_MAX_MM = 20.0  # material error drawn fully red, millimetres
CHART_BOUNDARY_COLOR = (255, 0, 255)  # pixels where the two meshes show different UV charts


def texcoord_image(ctx: GLContext, positions: np.ndarray, faces: np.ndarray, texcoords: np.ndarray,
                   camera: Camera) -> tuple[np.ndarray, Raster]:
    """Render per-vertex texcoords from a camera.

    Args:
        ctx: the GL context. positions: (n,3). faces: (m,3). texcoords: (n,2) per-vertex uv.

    Returns:
        (H,W,2) float32 uv per pixel (0 on background), and the `Raster` it came from
        (`.mask` is where the mesh covers the pixel).
    """
    from .raster import interpolate, rasterize

    raster = rasterize(ctx, np.asarray(positions, np.float64), np.asarray(faces), camera, attributes=True)
    return interpolate(np.asarray(texcoords, np.float64), raster, faces), raster


def chart_image(raster: Raster, faces: np.ndarray, charts: np.ndarray) -> np.ndarray:
    """(H,W) int64 UV chart label per pixel from per-vertex `charts` (n,) int; -1 on background."""
    label = np.full(raster.tri_id.shape, -1, np.int64)
    label[raster.mask] = np.asarray(charts)[np.asarray(faces)[raster.tri_id[raster.mask], 0]]
    return label


def masked_uv_error(uv_a: np.ndarray, mask_a: np.ndarray, uv_b: np.ndarray,
                    mask_b: np.ndarray) -> tuple[np.ndarray, float]:
    """Per-pixel ‖uv_a − uv_b‖ where both masks hold.

    Args:
        uv_a, uv_b: (H,W,2) uv images (`texcoord_image`). mask_a, mask_b: (H,W) bool.

    Returns:
        error (H,W) float32 (NaN outside both masks) and its SqrtMSE (NaN if no pixel).
    """
    both = mask_a & mask_b
    err = np.full(mask_a.shape, np.nan, np.float32)
    diff = uv_a[both].astype(np.float64) - uv_b[both].astype(np.float64)
    e = np.sqrt(np.einsum("ij,ij->i", diff, diff))
    err[both] = e
    return err, float(np.sqrt(np.mean(e ** 2))) if e.size else float("nan")


def uv_error_image(ctx: GLContext, gt_positions: np.ndarray, faces_gt: np.ndarray, uv_gt: np.ndarray,
                   inf_positions: np.ndarray, faces_inf: np.ndarray, texcoords_inf: np.ndarray,
                   camera: Camera) -> tuple[np.ndarray, float]:
    """Per-pixel uv error of an inferred mesh with given texcoords against the gt mesh.

    Args:
        ctx: the GL context.
        gt_positions: (n,3) gt positions; faces_gt (m,3); uv_gt (n,2) T_G.
        inf_positions: (n',3) inferred positions (subdivided when the texcoords are);
            faces_inf (m',3); texcoords_inf (n',2) (T_G for the baseline, T_N otherwise).
        camera: zero-distortion camera.

    Returns:
        error: (H,W) float32 ‖uv_inferred − uv_gt‖, NaN where not covered by both meshes.
        sqrt_mse: sqrt(mean error²) over the covered pixels (NaN if none).
    """
    uv_g, raster_g = texcoord_image(ctx, gt_positions, faces_gt, uv_gt, camera)
    uv_i, raster_i = texcoord_image(ctx, inf_positions, faces_inf, texcoords_inf, camera)
    return masked_uv_error(uv_i, raster_i.mask, uv_g, raster_g.mask)


class MaterialMap:
    """Texture coordinates -> the material point they name on the rest garment.

    The uv layout (faces, uv) is rasterized once in UV space into a triangle-id buffer;
    a query point's candidates are the id of its texel, else the ids of the 3x3 texels
    around it; exact float64 barycentrics decide, and the material point is the same
    barycentric combination of the rest positions. Points the candidates do not contain
    are retried with the triangles sharing a vertex with them (slivers thinner than a
    texel); points outside every triangle (off the charts) map to the nearest point of the
    layout's boundary edges. The layout is assumed not to overlap itself (one material
    point per uv), as a texture atlas is.

    Args:
        faces: (m,3) int triangles of the base mesh.
        uv: (n,2) float texture coordinates T_G (the layout).
        rest: (n,3) float rest positions in meters.
        resolution: texels per side of the id buffer.
        ctx: the GL context for the one UV rasterization (a new one when None).
    """

    def __init__(self, faces: np.ndarray, uv: np.ndarray, rest: np.ndarray, resolution: int = 2048, *,
                 ctx: GLContext | None = None):
        import scipy.sparse as sp

        from .raster import context_or_new, rasterize_uv

        self.faces = np.asarray(faces, dtype=np.int64)
        self.uv = np.asarray(uv, dtype=np.float64)
        self.rest = np.asarray(rest, dtype=np.float64)
        if self.rest.shape != (len(self.uv), 3):
            raise ValueError(f"rest must be ({len(self.uv)}, 3), got {self.rest.shape}")
        self.resolution = int(resolution)
        with context_or_new(ctx) as gl:
            self.ids = rasterize_uv(gl, self.uv, self.faces, self.resolution, self.resolution, attributes=False).tri_id
        m, n = len(self.faces), len(self.uv)
        incidence = sp.csr_matrix((np.ones(3 * m), (np.repeat(np.arange(m), 3), self.faces.ravel())), shape=(m, n))
        self.face_ring = (incidence @ incidence.T).tocsr()
        e = np.sort(self.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        edges, count = np.unique(e, axis=0, return_counts=True)
        self.boundary = edges[count == 1]

    def _barycentric(self, points: np.ndarray, tri: np.ndarray) -> np.ndarray:
        """(k,3) barycentrics of points (k,2) in uv triangles tri (k,)."""
        a, b, c = (self.uv[self.faces[tri, i]] for i in range(3))
        v0, v1, v2 = b - a, c - a, points - a
        det = v0[:, 0] * v1[:, 1] - v0[:, 1] * v1[:, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            w1 = (v2[:, 0] * v1[:, 1] - v2[:, 1] * v1[:, 0]) / det
            w2 = (v0[:, 0] * v2[:, 1] - v0[:, 1] * v2[:, 0]) / det
        bary = np.stack([1.0 - w1 - w2, w1, w2], axis=1)
        bary[~np.isfinite(bary).all(axis=1)] = -np.inf  # degenerate triangle: never contains
        return bary

    def _best(self, points: np.ndarray, point_index: np.ndarray, tri: np.ndarray, k: int):
        """Per point, the candidate triangle it is most inside of: (tri (k,), bary (k,3), inside (k,))."""
        bary = self._barycentric(points[point_index], tri)
        score = bary.min(axis=1)
        order = np.lexsort((-score, point_index))
        first = np.ones(len(order), bool)
        first[1:] = point_index[order][1:] != point_index[order][:-1]
        best = order[first]
        out_tri = np.full(k, -1, np.int64)
        out_bary = np.zeros((k, 3))
        inside = np.zeros(k, bool)
        p = point_index[best]
        out_tri[p], out_bary[p], inside[p] = tri[best], bary[best], score[best] >= -1e-9
        return out_tri, out_bary, inside

    def _nearest_on_boundary(self, points: np.ndarray) -> np.ndarray:
        """Rest positions of the nearest points on the layout's boundary edges, (k,3)."""
        a, b = self.uv[self.boundary[:, 0]], self.uv[self.boundary[:, 1]]
        ab = b - a
        length2 = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300)
        out = np.empty((len(points), 3))
        for start in range(0, len(points), 256):
            q = points[start:start + 256, None, :]
            t = np.clip(np.einsum("kej,ej->ke", q - a, ab) / length2, 0.0, 1.0)
            dist2 = np.sum((a + t[..., None] * ab - q) ** 2, axis=-1)
            e = np.argmin(dist2, axis=1)
            te = t[np.arange(len(e)), e][:, None]
            out[start:start + 256] = (1.0 - te) * self.rest[self.boundary[e, 0]] + te * self.rest[self.boundary[e, 1]]
        return out

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """Rest positions (k,3) float64 of the material points named by uv points (k,2)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        k, R = len(points), self.resolution
        col = np.clip(np.floor(points[:, 0] * R).astype(np.int64), 0, R - 1)
        row = np.clip(np.floor(points[:, 1] * R).astype(np.int64), 0, R - 1)
        # Most points lie in the triangle of their own texel: try that one first.
        tri = self.ids[row, col].astype(np.int64)
        bary = np.zeros((k, 3))
        has = np.flatnonzero(tri >= 0)
        bary[has] = self._barycentric(points[has], tri[has])
        inside = np.zeros(k, bool)
        inside[has] = bary[has].min(axis=1) >= -1e-9
        retry = np.flatnonzero(~inside)
        if retry.size:  # near an edge of the layout's raster: the 3x3 texels around
            offsets = np.arange(-1, 2)
            rows = np.clip(row[retry, None, None] + offsets[None, :, None], 0, R - 1)
            cols = np.clip(col[retry, None, None] + offsets[None, None, :], 0, R - 1)
            cand = self.ids[rows, cols].reshape(len(retry), -1)
            pi, slot = np.nonzero(cand >= 0)
            t2, b2, in2 = self._best(points[retry], pi, cand[pi, slot].astype(np.int64), len(retry))
            tri[retry], bary[retry], inside[retry] = t2, b2, in2
        retry = np.flatnonzero(~inside & (tri >= 0))
        if retry.size:  # slivers thinner than a texel: the triangles around the candidate
            ring = self.face_ring[tri[retry]].tocoo()
            t2, b2, in2 = self._best(points[retry], ring.row.astype(np.int64), ring.col.astype(np.int64), len(retry))
            better = in2 | (b2.min(axis=1) > bary[retry].min(axis=1))
            tri[retry[better]], bary[retry[better]], inside[retry[better]] = t2[better], b2[better], in2[better]
        out = np.empty((k, 3))
        ok = np.flatnonzero(inside)
        out[ok] = np.einsum("kj,kjc->kc", bary[ok], self.rest[self.faces[tri[ok]]])
        off = np.flatnonzero(~inside)
        if off.size:
            out[off] = self._nearest_on_boundary(points[off])
        return out


def _material_points(raster, faces: np.ndarray, rest: np.ndarray) -> np.ndarray:
    """Rest positions (k,3) float64 of the material each covered pixel shows (row-major order)."""
    mask = raster.mask
    corners = np.asarray(rest, np.float64)[np.asarray(faces)[raster.tri_id[mask]]]
    return np.einsum("kj,kjc->kc", raster.bary[mask].astype(np.float64), corners)


def _material_error(points_a: np.ndarray, mask_a: np.ndarray, points_b: np.ndarray,
                    mask_b: np.ndarray) -> tuple[np.ndarray, float]:
    """Per-pixel distance of two material-point images given on their masks' pixels."""
    full_a = np.zeros(mask_a.shape + (3,))
    full_b = np.zeros(mask_b.shape + (3,))
    full_a[mask_a], full_b[mask_b] = points_a, points_b
    both = mask_a & mask_b
    err = np.full(mask_a.shape, np.nan, np.float32)
    e = np.linalg.norm(full_a[both] - full_b[both], axis=1)
    err[both] = e
    return err, float(np.sqrt(np.mean(e ** 2))) if e.size else float("nan")


def material_error_image(ctx: GLContext, gt_positions: np.ndarray, faces_gt: np.ndarray, rest: np.ndarray,
                         inf_positions: np.ndarray, faces_inf: np.ndarray, texcoords_inf: np.ndarray, camera: Camera,
                         material_map: MaterialMap) -> tuple[np.ndarray, float]:
    """Per-pixel material error of an inferred mesh with given texcoords against the gt mesh.

    Args:
        ctx: the GL context.
        gt_positions: (n,3) gt positions; faces_gt (m,3); rest (n,3) rest positions (m).
        inf_positions: (n',3) inferred positions (subdivided when the texcoords are);
            faces_inf (m',3); texcoords_inf (n',2) (T_G for the baseline, T_N otherwise).
        camera: zero-distortion camera.
        material_map: `MaterialMap` of the dataset's uv layout (faces_gt, T_G, rest).

    Returns:
        error: (H,W) float32 distance on the rest garment between the material points the
            two meshes show, in meters; NaN where not covered by both meshes.
        rmse: sqrt(mean error²) over the covered pixels, meters (NaN if none).
    """
    from .raster import interpolate, rasterize

    r_g = rasterize(ctx, np.asarray(gt_positions, np.float64), np.asarray(faces_gt), camera)
    r_i = rasterize(ctx, np.asarray(inf_positions, np.float64), np.asarray(faces_inf), camera)
    uv_i = interpolate(np.asarray(texcoords_inf, np.float64), r_i, faces_inf)
    # float32 pixel uv, as `texcoord_image` gives it: the same texcoords the uv error measures.
    return _material_error(material_map(uv_i[r_i.mask]), r_i.mask, _material_points(r_g, faces_gt, rest), r_g.mask)


def _stats(values: Sequence[float]) -> dict:
    v = np.asarray([x for x in values if np.isfinite(x)], dtype=np.float64)
    if v.size == 0:
        return {"mean": float("nan"), "std": float("nan")}
    return {"mean": float(v.mean()), "std": float(v.std())}


def _summary(base: list[float], tc: list[float], base_same: list[float], tc_same: list[float],
             base_material: list[float] | None = None, tc_material: list[float] | None = None) -> dict:
    ok = [i for i in range(len(base)) if np.isfinite(base[i]) and np.isfinite(tc[i])]
    out = {"num_images": len(ok)}
    for key, ratio_key, (b, t) in (("sqrt_mse", "ratio", (base, tc)), ("sqrt_mse_same_chart", "ratio_same_chart",
                                                                         (base_same, tc_same)),
                                   ("material_rmse_m", "ratio_material", (base_material, tc_material))):
        if b is None:
            out[key] = out[ratio_key] = None
            continue
        sb, st = _stats([b[i] for i in ok]), _stats([t[i] for i in ok])
        out[key] = {"inferred": sb, "texcoords": st}
        out[ratio_key] = sb["mean"] / st["mean"] if ok and st["mean"] > 0 else float("nan")
    return out


@dataclass(frozen=True)
class _EvalSpec:
    """What a worker needs to evaluate images: picklable; its opened inputs are kept per thread by key."""

    dataset: str
    texcoords: str
    rig: Rig
    heatmaps: str | None

    @property
    def key(self) -> tuple[str, str]:
        return self.dataset, self.texcoords


@dataclass
class _EvalState:
    """A thread's opened inputs and GL context for one `_EvalSpec`."""

    dataset: Any
    texcoord_set: Any
    charts: np.ndarray
    charts_tc: np.ndarray
    ctx: Any
    material_map: MaterialMap | None
    owns_ctx: bool

    def release(self) -> None:
        if self.owns_ctx:
            self.ctx.release()


_EVAL_STATE = ThreadState()  # each thread's _EvalState, one set at a time


def _open_eval_state(ds, tc, ctx: GLContext, owns_ctx: bool) -> _EvalState:
    from .mesh import charts_through_parent, uv_charts

    charts = uv_charts(ds.faces, ds.num_vertices)
    material_map = MaterialMap(ds.faces, ds.uv, ds.rest, ctx=ctx) if ds.rest is not None else None
    return _EvalState(ds, tc, charts, charts_through_parent(charts, tc.faces, len(tc.uv)), ctx, material_map,
                      owns_ctx)


def _eval_state(spec: _EvalSpec) -> _EvalState:
    """A worker's state for an evaluation (one in this process puts its own in place up front)."""
    from .dataset import load_dataset
    from .raster import GLContext
    from .slide_jobs import single_thread_gl
    from .texcoords import open_texcoords

    single_thread_gl()
    ds = load_dataset(spec.dataset, validate=False)
    tc = open_texcoords(spec.texcoords, ds.num_vertices)
    return _open_eval_state(ds, tc, GLContext(), True)


def _eval_images(spec: _EvalSpec, jobs: list[tuple[int, int, str]]) -> list[tuple]:
    """Evaluate (job index, pose, camera name) images; returns (index, s_b, s_t, same_b,
    same_t, material_b, material_t) each (NaN material without a rest shape)."""
    from .io import read_row, save_png
    from .viz import colorbar, heatmap, side_by_side

    state = _EVAL_STATE.get(spec.key, lambda: _eval_state(spec))
    ds, tc, ctx, material_map = state.dataset, state.texcoord_set, state.ctx, state.material_map
    charts, charts_tc = state.charts, state.charts_tc
    out = []
    for index, k, name in jobs:
        cam = spec.rig[name]
        # Through the files (`read_row`): rows read through the dataset's maps stay resident.
        gt = read_row(ds.gt, k).astype(np.float64)
        inferred = read_row(ds.inferred, k).astype(np.float64)
        uv_g, raster_g = texcoord_image(ctx, gt, ds.faces, ds.uv, cam)
        uv_b, raster_b = texcoord_image(ctx, inferred, ds.faces, ds.uv, cam)
        uv_t, raster_t = texcoord_image(ctx, tc.positions(inferred), tc.faces, tc.texcoords(cam.name, k), cam)
        chart_g, chart_b = chart_image(raster_g, ds.faces, charts), chart_image(raster_b, ds.faces, charts)
        chart_t = chart_image(raster_t, tc.faces, charts_tc)
        err_b, s_b = masked_uv_error(uv_b, chart_b >= 0, uv_g, chart_g >= 0)
        err_t, s_t = masked_uv_error(uv_t, chart_t >= 0, uv_g, chart_g >= 0)
        same_b = masked_uv_error(uv_b, chart_b == chart_g, uv_g, chart_g >= 0)[1]
        same_t = masked_uv_error(uv_t, chart_t == chart_g, uv_g, chart_g >= 0)[1]
        mat_err_b = mat_err_t = None
        m_b = m_t = float("nan")
        if material_map is not None:
            m_g = _material_points(raster_g, ds.faces, ds.rest)
            mat_err_b, m_b = _material_error(_material_points(raster_b, ds.faces, ds.rest), raster_b.mask, m_g,
                                             raster_g.mask)
            mat_err_t, m_t = _material_error(material_map(uv_t[raster_t.mask]), raster_t.mask, m_g, raster_g.mask)
        out.append((index, s_b, s_t, same_b, same_t, m_b, m_t))
        if spec.heatmaps is not None:
            panels = []
            for err, chart, total, same in ((err_b, chart_b, s_b, same_b), (err_t, chart_t, s_t, same_t)):
                image = heatmap(err, HEATMAP_MAX)
                image[(chart >= 0) & (chart_g >= 0) & (chart != chart_g)] = CHART_BOUNDARY_COLOR
                panels.append((image, f"{total * 1e3:.2f}e-3, same chart {same * 1e3:.2f}e-3"))
            picture = side_by_side([panels[0][0], panels[1][0], colorbar(cam.height, HEATMAP_MAX, unit="uv")],
                                   [f"inferred {panels[0][1]}", f"{tc.source} {panels[1][1]}", ""])
            if material_map is not None:
                row = side_by_side([heatmap(mat_err_b * 1e3, MATERIAL_HEATMAP_MAX_MM),
                                    heatmap(mat_err_t * 1e3, MATERIAL_HEATMAP_MAX_MM),
                                    colorbar(cam.height, MATERIAL_HEATMAP_MAX_MM, unit="mm")],
                                   [f"inferred material {m_b * 1e3:.2f} mm", f"{tc.source} material {m_t * 1e3:.2f} mm",
                                    ""])
                picture = np.concatenate([picture, np.full((4, picture.shape[1], 3), 255, np.uint8), row])
            save_png(Path(spec.heatmaps) / f"pose_{k:05d}_{cam.name}.png", picture)
    return out


def evaluate(dataset, rig, texcoord_set, *, poses: Sequence[int] | None = None,
             heatmaps: str | os.PathLike | None = None, progress: bool = True, workers: int = 1,
             scheduler: str | None = None, ctx: GLContext | None = None) -> dict:
    """SqrtMSE of the baseline and of a texcoord set over poses and cameras (DESIGN §7).

    "inferred" is the baseline: the base inferred mesh with T_G. "texcoords" is the
    (subdivided) inferred mesh with the set's T_N for that camera. Images where the two
    meshes share no pixel are skipped.

    Args:
        dataset: `Dataset` or dataset directory.
        rig: `Rig` or rig path / built-in name. A rig whose cameras are all in the set
            selects those cameras; otherwise it must contain every camera of the set.
        texcoord_set: `TexcoordSet` or its directory.
        poses: dataset pose indices (default: the set's poses).
        heatmaps: if given, a directory that receives ``pose_<k>_<camera>.png`` per image:
            baseline and texcoords heatmaps side by side (blue = 0, red >= 0.04; magenta where
            the two meshes show different UV charts) and, when the dataset has `rest`, a
            second row with the material error in millimetres (red >= 20 mm).
        progress: progress bar on stderr.
        workers: local processes (1: this process), see `mvtex.parallel.map_unordered`.
        scheduler: Dask scheduler address (overrides `workers`); its workers must read the
            same dataset and texcoord paths.
        ctx: the GL context for work in this process (one is created, and released, for this
            call if None); worker processes create their own.
        The result does not depend on `workers` or `scheduler`: images are gathered back
        into (pose, camera) order before any statistic is taken.

    Returns:
        {"num_images", "sqrt_mse": {"inferred": {"mean", "std"}, "texcoords": {...}},
         "ratio": inferred mean / texcoords mean, "sqrt_mse_same_chart": {...},
         "ratio_same_chart", "material_rmse_m": {"inferred": {"mean", "std"}, "texcoords": {...}}
         (meters; None when the dataset has no `rest`), "ratio_material" (None likewise),
         "per_camera": {name: same keys}}.
    """
    from tqdm import tqdm

    from .camera import as_rig
    from .dataset import as_dataset
    from .parallel import map_unordered
    from .raster import GLContext
    from .texcoords import TexcoordSet, open_texcoords

    ds = as_dataset(dataset)
    tc = texcoord_set if isinstance(texcoord_set, TexcoordSet) else open_texcoords(texcoord_set, ds.num_vertices)
    if tc.num_base_vertices != ds.num_vertices:
        from .errors import InputError

        raise InputError(tc.path / "mesh.npz", f"made for {tc.num_base_vertices} vertices, the dataset has {ds.num_vertices}")
    rig, rig_source = as_rig(rig)
    if not set(rig.names) <= set(tc.cameras):
        rig = rig.select(tc.cameras, source=rig_source)
    poses = tc.poses if poses is None else [int(p) for p in poses]
    for p in poses:
        tc.row(p)  # InputError for a pose the set does not have
    for name in rig.names:
        tc.displacement(name, poses[0])  # validates the camera's arrays once, here
    out_dir = Path(heatmaps) if heatmaps is not None else None
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
    spec = _EvalSpec(dataset=str(Path(ds.path).resolve()), texcoords=str(Path(tc.path).resolve()), rig=rig,
                     heatmaps=None if out_dir is None else str(out_dir.resolve()))
    local = workers <= 1 and not scheduler
    if local:  # this process: reuse what is open
        own = GLContext() if ctx is None else None
        _EVAL_STATE.set(spec.key, _open_eval_state(ds, tc, own or ctx, own is not None))
    jobs = [(i, k, name) for i, (k, name) in enumerate((k, c.name) for k in poses for c in rig)]
    chunk = max(1, min(8, len(jobs) // (4 * max(1, workers))))
    tasks = [(spec, jobs[i:i + chunk]) for i in range(0, len(jobs), chunk)]
    values: list = [None] * len(jobs)
    try:
        with tqdm(total=len(jobs), desc="eval", unit="image", disable=not progress, file=sys.stderr) as bar:
            for results in map_unordered(_eval_images, tasks, workers=workers, scheduler=scheduler):
                for index, *image in results:
                    values[index] = image
                bar.update(len(results))
    finally:
        if local:
            _EVAL_STATE.set(None, None)
    has_rest = ds.rest is not None
    per_cam: dict[str, tuple[list, ...]] = {c.name: ([], [], [], [], [], []) for c in rig}
    for (_, _, name), image in zip(jobs, values):
        for column, value in zip(per_cam[name], image):
            column.append(value)
    result = _summary(*([v for c in per_cam.values() for v in c[i]] if i < 4 or has_rest else None for i in range(6)))
    result["per_camera"] = {name: _summary(*lists[:4], *(lists[4:] if has_rest else (None, None)))
                            for name, lists in per_cam.items()}
    return result
