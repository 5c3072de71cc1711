"""The per-pixel texture-coordinate error (DESIGN §5 "Per-pixel error", the paper's SqrtMSE):
uv images of a mesh from a camera, their difference over the pixels both meshes cover.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from mvtex.data.camera import Camera
from mvtex.render.raster import interpolate, rasterize

if TYPE_CHECKING:
    from mvtex.render.context import GLContext
    from mvtex.render.raster import Raster


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
