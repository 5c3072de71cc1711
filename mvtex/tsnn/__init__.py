"""Texture sliding networks (TSNN): one network per camera maps a pose vector to a
displacement image over the UV atlas; per-vertex displacements are read from it by
bilinear sampling at T_G.

    atlas     per-vertex values <-> atlas images (rasterize in UV, sample with grid_sample)
    model     the decoder: pose -> linear -> transposed-convolution stages -> (2, R, R)
    train     `train_camera`: one camera's network from a texcoord set
    predict   `predict`: camera networks -> a texcoord set ("source": "tsnn")

Importing this package is light; torch loads inside the functions that need it.
"""

from __future__ import annotations

from typing import Any

# `predict` is deliberately not re-exported: the name is the submodule
# (`from mvtex.tsnn.predict import predict`).
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
