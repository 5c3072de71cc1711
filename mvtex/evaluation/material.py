"""The material error: at a pixel, the distance on the rest garment between the material
points the two meshes show (texcoords located in the uv layout and mapped back to `rest`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp

from mvtex.data.camera import Camera
from mvtex.evaluation.kernels import locate
from mvtex.render.context import context_or_new
from mvtex.render.raster import check_mesh, interpolate, rasterize, rasterize_uv
from mvtex.util.checks import as_array, as_index, check_shape
from mvtex.util.errors import OptionError

if TYPE_CHECKING:
    from mvtex.render.context import GLContext


MATERIAL_HEATMAP_MAX_MM = 20.0  # material error drawn fully red, millimeters


class MaterialMap:
    """Texture coordinates -> the material point they name on the rest garment.

    The uv layout (faces, uv) is rasterized once in UV space into a triangle-id buffer;
    a query point's candidates are the id of its texel, else the ids of the 3x3 texels
    around it; exact float64 barycentrics decide (`mvtex.evaluation.kernels.locate`), and the material point is the same
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

        uv, faces = check_mesh(uv, faces, "uv", dims=2)
        self.faces = faces.astype(np.int64)
        self.uv = uv
        self.rest = as_array(rest, "rest")
        check_shape(self.rest, "rest", (len(self.uv), 3))
        if not np.all(np.isfinite(self.rest)):
            raise OptionError("rest", "has NaN or infinite values")
        self.resolution = as_index(resolution, "resolution")
        if not 16 <= self.resolution <= 8192:
            raise OptionError("resolution", f"must be in 16..8192, got {self.resolution}")
        with context_or_new(ctx) as gl:
            self.ids = rasterize_uv(gl, self.uv, self.faces, self.resolution, self.resolution, attributes=False).tri_id
        m, n = len(self.faces), len(self.uv)
        incidence = sp.csr_matrix((np.ones(3 * m), (np.repeat(np.arange(m), 3), self.faces.ravel())), shape=(m, n))
        self.face_ring = (incidence @ incidence.T).tocsr()
        self.face_ring.sort_indices()
        e = np.sort(self.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        edges, count = np.unique(e, axis=0, return_counts=True)
        self.boundary = edges[count == 1]

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

        points = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 2))
        out, inside = locate(points, self.ids, self.faces, self.uv, self.rest, self.face_ring.indptr,
                             self.face_ring.indices)
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

    r_g = rasterize(ctx, np.asarray(gt_positions, np.float64), np.asarray(faces_gt), camera)
    r_i = rasterize(ctx, np.asarray(inf_positions, np.float64), np.asarray(faces_inf), camera)
    uv_i = interpolate(np.asarray(texcoords_inf, np.float64), r_i, faces_inf)
    # float32 pixel uv, as `texcoord_image` gives it: the same texcoords the uv error measures.
    return _material_error(material_map(uv_i[r_i.mask]), r_i.mask, _material_points(r_g, faces_gt, rest), r_g.mask)
