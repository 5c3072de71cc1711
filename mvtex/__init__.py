"""mvtex: texture sliding for learned cloth, multi-view reconstruction and COLMAP export.

Layers (imports point down only; docs/architecture.md has the full map):
    errors, io, resources, parallel, viz, mesh  -> files, pictures, mesh topology
    camera, dataset, texcoords                  -> cameras, datasets, texcoord sets
    raster, extrapolate, synth                  -> GL (a GLContext passed first), fill, built-in data
    sliding                                     -> texture sliding of one (pose, camera)
    slide_jobs, metrics, render, recon, tsnn    -> whole datasets, evaluation, reconstruction, networks
    colmap, ply                                 -> exporters
    demo, cli                                   -> the pipeline; argument parsing only

`import mvtex` needs numpy only; heavy libraries load inside the module that uses them.
"""

__version__ = "0.1.0"

from mvtex.util.errors import InputError

__all__ = ["InputError", "__version__"]
