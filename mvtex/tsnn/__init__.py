"""Texture sliding networks (TSNN): a network maps what is known at inference time (the
pose, the inferred mesh X_N, the camera) to a displacement image over the UV atlas;
per-vertex displacements are read from it by bilinear sampling at T_G.

    atlas     per-vertex values <-> atlas images (rasterize in UV, sample with grid_sample)
    geometry  geometry images of X_N: positions, normals, strain along u and v, curvature
    model     `UNet` (default: geometry images [+ the camera's view] + pose -> image) and
              `TSNN` (the paper's: pose -> linear -> transposed convolutions -> image)
    train     `train`: one camera's network, or one for every camera conditioned on the view
    predict   `predict`: networks -> a texcoord set ("source": "tsnn") for their own
              cameras or for any rig

Importing this package is light; torch loads inside the functions that need it.
"""

from __future__ import annotations

from typing import Any

# `train` and `predict` are deliberately not re-exported: the names are the submodules
# (`from mvtex.tsnn.train import train`, `from mvtex.tsnn.predict import predict`).
__all__ = ["TrainOptions", "train_camera", "load_model", "AtlasSampler"]


def __getattr__(name: str) -> Any:
    # Lazy re-exports: `from mvtex.tsnn import train_camera` without importing torch up front.
    if name in ("TrainOptions", "train_camera"):
        from . import train

        return getattr(train, name)
    if name == "load_model":
        from .predict import load_model

        return load_model
    if name == "AtlasSampler":
        from . import atlas

        return atlas.AtlasSampler
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
