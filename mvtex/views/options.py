"""The options of novel views, previews and scenes (`ViewOptions`, `PreviewOptions`,
`ExportOptions`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from mvtex.util.options import Options, knob

METHODS = ("blend", "reconstruct")

_METHOD_HELP = ("blend: blend the array's texcoords (the paper); reconstruct: read the material where the view's "
                "rays meet the reconstruction")


@dataclass(frozen=True)
class ViewOptions(Options):
    """Options of `novel_views` (the `mvtex views` flags are made from them).

    Attributes:
        method: "blend" or "reconstruct" (see `mvtex.views.synthesizer`).
        uv_resolution: texels per side of the UV lookup that finds the hit triangle.
    """

    method: Literal["blend", "reconstruct"] = knob("reconstruct", _METHOD_HELP)
    uv_resolution: int = knob(1024, "texels per side of the UV lookup that finds the hit triangle", low=16,
                              high=8192)


@dataclass(frozen=True)
class PreviewOptions(Options):
    """Options of `stereo_preview` (the `mvtex preview` flags are made from them).

    Attributes:
        ipd: distance between the eyes (m).
        method: "blend" or "reconstruct" (as in `mvtex.views.synthesizer`).
        path: also write path.gif.
        frames_per_segment: GIF frames between two consecutive array cameras.
        margin: pixels added around the garment's bounding box for SSIM/PSNR.
    """

    ipd: float = knob(0.064, "distance between the eyes", unit="m", low=0, high=10, high_open=True)
    method: Literal["blend", "reconstruct"] = knob("reconstruct", "how each eye's texcoords are computed: "
                                                   + _METHOD_HELP)
    path: bool = knob(False, "also write path.gif: the viewpoint moving across the array")
    frames_per_segment: int = knob(6, "GIF frames between two consecutive array cameras", low=1, high=240)
    margin: int = knob(4, "pixels added around the garment's bounding box for SSIM and PSNR", unit="px", low=0,
                       high=4096)


MAX_TEXTURE_SIZE = 4096


@dataclass(frozen=True)
class ExportOptions(Options):
    """Options of `export_scene` (the `mvtex export` flags are made from them).

    Attributes:
        texture_size: pixels per side of the fabric texture written into the scene (the
            renders' texture is 1024).
        viewer: also write viewer.html.
    """

    texture_size: int = knob(1024, "pixels per side of the fabric texture in the scene", low=64,
                             high=MAX_TEXTURE_SIZE)
    viewer: bool = knob(True, "write viewer.html (--no-viewer: the scene alone)")
