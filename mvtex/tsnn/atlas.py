"""Images over the UV atlas: per-vertex values <-> (C, H, W) images.

Convention (the same as `mvtex.render.raster.rasterize_uv`): texel (row r, column c) of an H x W
atlas image has its centre at (u, v) = ((c + 0.5)/W, (r + 0.5)/H). Row 0 is v ≈ 0 (GL
texture order, *not* picture order: flip rows to show v up). With that convention the
`torch.nn.functional.grid_sample` coordinate of a texcoord is simply 2·uv − 1
(`align_corners=False`: −1 and +1 are the outer edges of the first and last texel).

Charts must not overlap in uv: one texel can hold one value only. `AtlasSampler` refuses an
atlas whose triangles share texel centres.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.ndimage import distance_transform_edt

from mvtex.data.mesh import barycentric_2d
from mvtex.render.context import GLContext
from mvtex.render.raster import Raster, interpolate, rasterize_uv
from mvtex.util.errors import InputError

if TYPE_CHECKING:
    from mvtex.render.context import GLContext


def vertex_grid(uv: np.ndarray):
    """`grid_sample` coordinates (1,1,n,2) float32 torch tensor of texcoords (n,2): 2·uv − 1."""
    import torch  # noqa: PLC0415 (loaded on use)

    return torch.from_numpy(2.0 * np.asarray(uv, dtype=np.float32) - 1.0).view(1, 1, -1, 2)


def sample_atlas(images, grid):
    """Read atlas images at texcoords with bilinear interpolation (GL-free).

    Args:
        images: (B,C,H,W) torch tensor, row 0 at v ≈ 0.
        grid: `vertex_grid(uv)` (1,1,n,2) on the images' device.

    Returns:
        (B,n,C) tensor, differentiable with respect to `images`.
    """
    import torch.nn.functional as F  # noqa: PLC0415 (loaded on use)

    g = grid.to(images.dtype).expand(images.shape[0], -1, -1, -1)
    out = F.grid_sample(images, g, mode="bilinear", padding_mode="border", align_corners=False)
    return out[:, :, 0, :].transpose(1, 2)


def uv_overlap(ctx: GLContext, uv: np.ndarray, faces: np.ndarray, resolution: int) -> np.ndarray:
    """Texels whose centre lies inside two or more uv triangles.

    `rasterize_uv` keeps the last triangle drawn on a texel. Drawing the faces once in
    order and once reversed therefore gives the same triangle on every texel covered once
    (GL's fill rule gives a texel centre on a shared edge to exactly one of the two
    triangles, whatever the order) and different triangles wherever two or more cover it.

    Args:
        ctx: the GL context.
        uv: (n,2) float texcoords in [0,1]². faces: (m,3) int.
        resolution: image size R (R x R texels).

    Returns:
        (R,R) bool, True on texels covered more than once (row 0 at v ≈ 0).
    """

    faces = np.asarray(faces)
    forward = rasterize_uv(ctx, uv, faces, resolution, resolution, attributes=False).tri_id
    backward = rasterize_uv(ctx, uv, faces[::-1], resolution, resolution, attributes=False).tri_id
    backward = np.where(backward >= 0, len(faces) - 1 - backward, -1)
    return forward != backward


@dataclass(frozen=True)
class AtlasLayout:
    """Where every texel of an atlas image gets its value from.

    Attributes:
        tri_id: (H,W) int32 triangle whose (possibly extrapolated) linear function fills the
            texel; -1 for texels further than `dilation` texels from every chart.
        bary: (H,W,3) float32 barycentrics of the texel centre in that triangle. Inside a
            chart they are the rasterizer's (all in [0,1]); on the dilated ring around a
            chart they are those of the nearest covered texel's triangle, unclamped, so a
            linear field continues linearly past the border.
        covered: (H,W) bool, True where a triangle covers the texel centre.
    """

    tri_id: np.ndarray
    bary: np.ndarray
    covered: np.ndarray


class AtlasSampler:
    """Per-vertex values <-> atlas images for one mesh and one resolution.

    Args:
        faces: (m,3) int triangle indices.
        uv: (n,2) float texcoords T_G in [0,1]²; charts must not overlap.
        resolution: atlas size R (images are R x R).
        dilation: texels to extend every chart by when making an image, so that bilinear
            sampling at a border vertex (which reads the 2x2 texels around it) reads values of
            its own chart, never background.
        source: file the atlas comes from, named in errors.
        ctx: the GL context for the two rasterizations in UV done here (one is created, and
            released, if None). Nothing else of the sampler uses GL.

    Raises:
        InputError: uv outside [0,1]² or overlapping charts.
    """

    def __init__(self, faces: np.ndarray, uv: np.ndarray, resolution: int, *, dilation: int = 2,
                 source: str | os.PathLike | None = None, ctx: GLContext | None = None):

        self.faces = np.asarray(faces, dtype=np.int32)
        self.uv = np.asarray(uv, dtype=np.float32)
        self.resolution = int(resolution)
        self.dilation = int(dilation)
        self.source = source
        if self.resolution < 2:
            raise ValueError(f"resolution must be at least 2, got {resolution}")
        if self.uv.ndim != 2 or self.uv.shape[1] != 2 or not np.all(np.isfinite(self.uv)):
            raise InputError(source, f"uv must be finite (n,2), got {self.uv.shape}")
        if self.uv.min() < 0 or self.uv.max() > 1:
            raise InputError(source, f"uv outside [0,1]² (range {self.uv.min():.4g}..{self.uv.max():.4g}): "
                             "atlas images cover the unit square only")
        if ctx is None:
            with GLContext() as own:
                overlap = uv_overlap(own, self.uv, self.faces, self.resolution)
                raster = rasterize_uv(own, self.uv, self.faces, self.resolution, self.resolution)
        else:
            overlap = uv_overlap(ctx, self.uv, self.faces, self.resolution)
            raster = rasterize_uv(ctx, self.uv, self.faces, self.resolution, self.resolution)
        if overlap.any():
            rows, cols = np.nonzero(overlap)
            raise InputError(source, f"uv charts overlap on {int(overlap.sum())} texels of a "
                             f"{self.resolution}x{self.resolution} atlas (first at u={(cols[0] + 0.5) / self.resolution:.4f}, "
                             f"v={(rows[0] + 0.5) / self.resolution:.4f}); one texel cannot hold two displacements")
        self.layout = self._dilate(raster.tri_id, raster.bary)
        self._raster = Raster(tri_id=self.layout.tri_id, bary=self.layout.bary, depth=None)

    def _dilate(self, tri_id: np.ndarray, bary: np.ndarray) -> AtlasLayout:

        covered = tri_id >= 0
        if not covered.any():
            raise InputError(self.source, f"no texel centre of the {self.resolution}² atlas lies inside a uv triangle")
        dist, (nr, nc) = distance_transform_edt(~covered, return_indices=True)
        ring = ~covered & (dist <= self.dilation)
        tri = np.where(covered, tri_id, -1).astype(np.int32)
        out_bary = np.where(covered[..., None], bary, 0).astype(np.float32)
        rr, cc = np.nonzero(ring)
        t = tri_id[nr[rr, cc], nc[rr, cc]]
        centres = np.stack([(cc + 0.5) / self.resolution, (rr + 0.5) / self.resolution], axis=1)
        tri[rr, cc] = t
        out_bary[rr, cc] = barycentric_2d(centres, self.uv[self.faces[t]].astype(np.float64))
        return AtlasLayout(tri_id=tri, bary=out_bary, covered=covered)

    @property
    def num_vertices(self) -> int:
        return len(self.uv)

    def to_image(self, values: np.ndarray) -> np.ndarray:
        """Rasterize per-vertex values into an atlas image.

        Args:
            values: (n,C) per-vertex values.

        Returns:
            (H,W,C) float32, linear inside each triangle, continued linearly `dilation` texels
            past chart borders, 0 elsewhere. Row 0 is v ≈ 0.
        """

        values = np.asarray(values)
        if values.ndim != 2 or values.shape[0] != self.num_vertices:
            raise ValueError(f"expected ({self.num_vertices},C) values, got {values.shape}")
        return interpolate(values, self._raster, self.faces)

    def grid(self):
        """The `grid_sample` grid of the vertices' T_G, (1,1,n,2) float32 torch tensor in [-1,1]."""
        return vertex_grid(self.uv)

    def sample(self, images, grid=None):
        """Read atlas images at every vertex's T_G with bilinear interpolation.

        Args:
            images: (B,C,H,W) torch tensor (row 0 at v ≈ 0), H = W = resolution.
            grid: the result of `grid()` already on the images' device (saves a copy per call).

        Returns:
            (B,n,C) tensor, differentiable with respect to `images`.
        """
        if grid is None:
            grid = self.grid().to(images.device)
        return sample_atlas(images, grid)

    def sample_numpy(self, image: np.ndarray) -> np.ndarray:
        """`sample` for one (H,W,C) numpy image; returns (n,C) float32."""
        import torch  # noqa: PLC0415 (loaded on use)

        t = torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32)).permute(2, 0, 1)[None]
        with torch.no_grad():
            return self.sample(t)[0].numpy()
