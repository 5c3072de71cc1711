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
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np

from .camera import Camera

if TYPE_CHECKING:
    from .raster import GLContext, Raster

HEATMAP_MAX = 0.04
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


def evaluate(dataset, rig, texcoord_set, *, poses: Sequence[int] | None = None,
             heatmaps: str | os.PathLike | None = None, progress: bool = True,
             ctx: GLContext | None = None) -> dict:
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
            the two meshes show different UV charts).
        progress: progress bar on stderr.
        ctx: the GL context (one is created, and released, for this call if None).

    Returns:
        {"num_images", "sqrt_mse": {"inferred": {"mean", "std"}, "texcoords": {...}},
         "ratio": inferred mean / texcoords mean, "sqrt_mse_same_chart": {...},
         "ratio_same_chart", "per_camera": {name: same keys}}.
    """
    from .camera import as_rig
    from .dataset import as_dataset
    from .raster import GLContext
    from .texcoords import TexcoordSet, open_texcoords

    if ctx is None:
        with GLContext() as own:
            return evaluate(dataset, rig, texcoord_set, poses=poses, heatmaps=heatmaps, progress=progress, ctx=own)
    from tqdm import tqdm

    from .io import save_png
    from .viz import colorbar, heatmap, side_by_side

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
    out_dir = Path(heatmaps) if heatmaps is not None else None
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
    from .mesh import charts_through_parent, uv_charts

    charts = uv_charts(ds.faces, ds.num_vertices)
    charts_tc = charts_through_parent(charts, tc.faces, len(tc.uv))
    per_cam: dict[str, tuple[list, ...]] = {c.name: ([], [], [], []) for c in rig}
    jobs = [(k, cam) for k in poses for cam in rig]
    for k, cam in tqdm(jobs, desc="eval", unit="image", disable=not progress, file=sys.stderr):
        gt = np.asarray(ds.gt[k], np.float64)
        inferred = np.asarray(ds.inferred[k], np.float64)
        uv_g, raster_g = texcoord_image(ctx, gt, ds.faces, ds.uv, cam)
        uv_b, raster_b = texcoord_image(ctx, inferred, ds.faces, ds.uv, cam)
        uv_t, raster_t = texcoord_image(ctx, tc.positions(inferred), tc.faces, tc.texcoords(cam.name, k), cam)
        chart_g, chart_b = chart_image(raster_g, ds.faces, charts), chart_image(raster_b, ds.faces, charts)
        chart_t = chart_image(raster_t, tc.faces, charts_tc)
        err_b, s_b = masked_uv_error(uv_b, chart_b >= 0, uv_g, chart_g >= 0)
        err_t, s_t = masked_uv_error(uv_t, chart_t >= 0, uv_g, chart_g >= 0)
        same_b = masked_uv_error(uv_b, chart_b == chart_g, uv_g, chart_g >= 0)[1]
        same_t = masked_uv_error(uv_t, chart_t == chart_g, uv_g, chart_g >= 0)[1]
        for values, value in zip(per_cam[cam.name], (s_b, s_t, same_b, same_t)):
            values.append(value)
        if out_dir is not None:
            panels = []
            for err, chart, total, same in ((err_b, chart_b, s_b, same_b), (err_t, chart_t, s_t, same_t)):
                image = heatmap(err, HEATMAP_MAX)
                image[(chart >= 0) & (chart_g >= 0) & (chart != chart_g)] = CHART_BOUNDARY_COLOR
                panels.append((image, f"{total * 1e3:.2f}e-3, same chart {same * 1e3:.2f}e-3"))
            picture = side_by_side([panels[0][0], panels[1][0], colorbar(cam.height, HEATMAP_MAX)],
                                   [f"inferred {panels[0][1]}", f"{tc.source} {panels[1][1]}", "e"])
            save_png(out_dir / f"pose_{k:05d}_{cam.name}.png", picture)
    result = _summary(*([v for c in per_cam.values() for v in c[i]] for i in range(4)))
    result["per_camera"] = {name: _summary(*lists) for name, lists in per_cam.items()}
    return result
