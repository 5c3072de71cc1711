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
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from .camera import Camera, Rig

HEATMAP_MAX = 0.04
CHART_BOUNDARY_COLOR = (255, 0, 255)  # pixels where the two meshes show different UV charts


def uv_image(positions: np.ndarray, faces: np.ndarray, texcoords: np.ndarray, camera: Camera,
             charts: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Render per-vertex texcoords.

    Returns:
        (H,W,2) float32 uv per pixel, and the (H,W) bool mask — or, when per-vertex `charts`
        (n,) int are given, the (H,W) int64 chart label per pixel (-1 on background).
    """
    from .raster import interpolate, rasterize

    raster = rasterize(np.asarray(positions, np.float64), np.asarray(faces), camera, attributes=True)
    uv = interpolate(np.asarray(texcoords, np.float64), raster, faces)
    if charts is None:
        return uv, raster.mask
    label = np.full(raster.tri_id.shape, -1, np.int64)
    label[raster.mask] = np.asarray(charts)[np.asarray(faces)[raster.tri_id[raster.mask], 0]]
    return uv, label


def _error(uv_a: np.ndarray, mask_a: np.ndarray, uv_b: np.ndarray, mask_b: np.ndarray) -> tuple[np.ndarray, float]:
    both = mask_a & mask_b
    err = np.full(mask_a.shape, np.nan, np.float32)
    diff = uv_a[both].astype(np.float64) - uv_b[both].astype(np.float64)
    e = np.sqrt(np.einsum("ij,ij->i", diff, diff))
    err[both] = e
    return err, float(np.sqrt(np.mean(e ** 2))) if e.size else float("nan")


def uv_error_image(gt_positions: np.ndarray, faces_gt: np.ndarray, uv_gt: np.ndarray, inf_positions: np.ndarray,
                   faces_inf: np.ndarray, texcoords_inf: np.ndarray, camera: Camera) -> tuple[np.ndarray, float]:
    """Per-pixel uv error of an inferred mesh with given texcoords against the gt mesh.

    Args:
        gt_positions: (n,3) gt positions; faces_gt (m,3); uv_gt (n,2) T_G.
        inf_positions: (n',3) inferred positions (subdivided when the texcoords are);
            faces_inf (m',3); texcoords_inf (n',2) (T_G for the baseline, T_N otherwise).
        camera: zero-distortion camera.

    Returns:
        error: (H,W) float32 ‖uv_inferred − uv_gt‖, NaN where not covered by both meshes.
        sqrt_mse: sqrt(mean error²) over the covered pixels (NaN if none).
    """
    uv_g, mask_g = uv_image(gt_positions, faces_gt, uv_gt, camera)
    uv_i, mask_i = uv_image(inf_positions, faces_inf, texcoords_inf, camera)
    return _error(uv_i, mask_i, uv_g, mask_g)


def _stats(values: Sequence[float]) -> dict:
    v = np.asarray([x for x in values if np.isfinite(x)], dtype=np.float64)
    if v.size == 0:
        return {"mean": float("nan"), "std": float("nan")}
    return {"mean": float(v.mean()), "std": float(v.std())}


def _summary(base: list[float], tc: list[float], base_same: list[float], tc_same: list[float]) -> dict:
    ok = [i for i in range(len(base)) if np.isfinite(base[i]) and np.isfinite(tc[i])]
    out = {"num_images": len(ok)}
    for key, ratio_key, (b, t) in (("sqrt_mse", "ratio", (base, tc)), ("sqrt_mse_same_chart", "ratio_same_chart",
                                                                         (base_same, tc_same))):
        sb, st = _stats([b[i] for i in ok]), _stats([t[i] for i in ok])
        out[key] = {"inferred": sb, "texcoords": st}
        out[ratio_key] = sb["mean"] / st["mean"] if ok and st["mean"] > 0 else float("nan")
    return out


@dataclass(frozen=True)
class _EvalSpec:
    """What a worker needs to evaluate images: picklable; opened inputs cached per process."""

    dataset: str
    texcoords: str
    rig: Rig
    heatmaps: str | None

    @property
    def key(self) -> tuple[str, str]:
        return self.dataset, self.texcoords


_EVAL_STATE: dict = {}


def _eval_state(spec: _EvalSpec):
    if spec.key not in _EVAL_STATE:
        from .dataset import load_dataset
        from .mesh import charts_through_parent, uv_charts
        from .texcoords import open_texcoords

        ds = load_dataset(spec.dataset, validate=False)
        tc = open_texcoords(spec.texcoords, ds.num_vertices)
        charts = uv_charts(ds.faces, ds.num_vertices)
        _EVAL_STATE.clear()
        _EVAL_STATE[spec.key] = (ds, tc, charts, charts_through_parent(charts, tc.faces, len(tc.uv)))
    return _EVAL_STATE[spec.key]


def _eval_images(spec: _EvalSpec, jobs: list[tuple[int, int, str]]) -> list[tuple]:
    """Evaluate (job index, pose, camera name) images; returns (index, s_b, s_t, same_b, same_t) each."""
    from .io import save_png
    from .viz import colorbar, heatmap, side_by_side

    ds, tc, charts, charts_tc = _eval_state(spec)
    out = []
    for index, k, name in jobs:
        cam = spec.rig[name]
        gt = np.asarray(ds.gt[k], np.float64)
        inferred = np.asarray(ds.inferred[k], np.float64)
        uv_g, chart_g = uv_image(gt, ds.faces, ds.uv, cam, charts)
        uv_b, chart_b = uv_image(inferred, ds.faces, ds.uv, cam, charts)
        err_b, s_b = _error(uv_b, chart_b >= 0, uv_g, chart_g >= 0)
        uv_t, chart_t = uv_image(tc.positions(inferred), tc.faces, tc.texcoords(cam.name, k), cam, charts_tc)
        err_t, s_t = _error(uv_t, chart_t >= 0, uv_g, chart_g >= 0)
        same_b = _error(uv_b, chart_b == chart_g, uv_g, chart_g >= 0)[1]
        same_t = _error(uv_t, chart_t == chart_g, uv_g, chart_g >= 0)[1]
        out.append((index, s_b, s_t, same_b, same_t))
        if spec.heatmaps is not None:
            panels = []
            for err, chart, total, same in ((err_b, chart_b, s_b, same_b), (err_t, chart_t, s_t, same_t)):
                image = heatmap(err, HEATMAP_MAX)
                image[(chart >= 0) & (chart_g >= 0) & (chart != chart_g)] = CHART_BOUNDARY_COLOR
                panels.append((image, f"{total * 1e3:.2f}e-3, same chart {same * 1e3:.2f}e-3"))
            picture = side_by_side([panels[0][0], panels[1][0], colorbar(cam.height, HEATMAP_MAX)],
                                   [f"inferred {panels[0][1]}", f"{tc.source} {panels[1][1]}", "e"])
            save_png(Path(spec.heatmaps) / f"pose_{k:05d}_{cam.name}.png", picture)
    return out


def evaluate(dataset, rig, texcoords, *, poses: Sequence[int] | None = None, heatmaps: str | os.PathLike | None = None,
             progress: bool = True, workers: int = 1, scheduler: str | None = None) -> dict:
    """SqrtMSE of the baseline and of a texcoord set over poses and cameras (DESIGN §7).

    "inferred" is the baseline: the base inferred mesh with T_G. "texcoords" is the
    (subdivided) inferred mesh with the set's T_N for that camera. Images where the two
    meshes share no pixel are skipped.

    Args:
        dataset: `Dataset` or dataset directory.
        rig: `Rig` or rig path / built-in name. A rig whose cameras are all in the set
            selects those cameras; otherwise it must contain every camera of the set.
        texcoords: `TexcoordSet` or its directory.
        poses: dataset pose indices (default: the set's poses).
        heatmaps: if given, a directory that receives ``pose_<k>_<camera>.png`` per image:
            baseline and texcoords heatmaps side by side (blue = 0, red >= 0.04; magenta where
            the two meshes show different UV charts).
        progress: progress bar on stderr.
        workers: local processes (1: this process), see `mvtex.parallel.map_unordered`.
        scheduler: Dask scheduler address (overrides `workers`); its workers must read the
            same dataset and texcoord paths.
        The result does not depend on `workers` or `scheduler`: images are gathered back
        into (pose, camera) order before any statistic is taken.

    Returns:
        {"num_images", "sqrt_mse": {"inferred": {"mean", "std"}, "texcoords": {...}},
         "ratio": inferred mean / texcoords mean, "sqrt_mse_same_chart": {...},
         "ratio_same_chart", "per_camera": {name: same keys}}.
    """
    from tqdm import tqdm

    from .camera import load_rig, resolve_rig
    from .dataset import Dataset, load_dataset
    from .parallel import map_unordered
    from .texcoords import TexcoordSet, open_texcoords

    ds = dataset if isinstance(dataset, Dataset) else load_dataset(dataset)
    tc = texcoords if isinstance(texcoords, TexcoordSet) else open_texcoords(texcoords, ds.num_vertices)
    if tc.num_base_vertices != ds.num_vertices:
        from .errors import InputError

        raise InputError(tc.path / "mesh.npz", f"made for {tc.num_base_vertices} vertices, the dataset has {ds.num_vertices}")
    rig_source = None
    if not isinstance(rig, Rig):
        rig_source = resolve_rig(rig)
        rig = load_rig(rig_source)
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
    from .mesh import charts_through_parent, uv_charts

    if workers <= 1 and not scheduler:  # this process: reuse what is open
        charts = uv_charts(ds.faces, ds.num_vertices)
        _EVAL_STATE.clear()
        _EVAL_STATE[spec.key] = (ds, tc, charts, charts_through_parent(charts, tc.faces, len(tc.uv)))
    jobs = [(i, k, name) for i, (k, name) in enumerate((k, c.name) for k in poses for c in rig)]
    chunk = max(1, min(8, len(jobs) // (4 * max(1, workers))))
    tasks = [(spec, jobs[i:i + chunk]) for i in range(0, len(jobs), chunk)]
    values: list = [None] * len(jobs)
    with tqdm(total=len(jobs), desc="eval", unit="image", disable=not progress, file=sys.stderr) as bar:
        for results in map_unordered(_eval_images, tasks, workers=workers, scheduler=scheduler):
            for index, *image in results:
                values[index] = image
            bar.update(len(results))
    per_cam: dict[str, tuple[list, ...]] = {c.name: ([], [], [], []) for c in rig}
    for (_, _, name), image in zip(jobs, values):
        for column, value in zip(per_cam[name], image):
            column.append(value)
    result = _summary(*([v for c in per_cam.values() for v in c[i]] for i in range(4)))
    result["per_camera"] = {name: _summary(*lists) for name, lists in per_cam.items()}
    return result
