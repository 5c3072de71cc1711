"""mvtex: texture sliding for learned cloth, multi-view reconstruction and COLMAP export.

Layers (imports point down only):
    camera, mesh, dataset, texcoords, io   -> plain numpy data and files
    raster                                 -> moderngl (EGL) rasterization
    sliding, extrapolate                   -> texture sliding per (pose, camera)
    metrics, recon, views, tsnn            -> evaluation, reconstruction, networks
    colmap, ply, viz, render               -> exporters and pictures
    cli                                    -> argument parsing only

`import mvtex` needs numpy only; heavy libraries load inside the module that uses them.
"""

__version__ = "0.1.0"

from .errors import InputError

__all__ = ["InputError", "__version__"]
