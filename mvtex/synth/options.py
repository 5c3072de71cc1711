"""The options of the built-in datasets (`SynthOptions`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from mvtex.util.checks import MAX_SEED
from mvtex.util.options import Options, knob

GARMENTS = ("shirt", "skirt")


MAX_POSES = 100_000  # most poses one dataset holds (checked before anything is allocated)


@dataclass(frozen=True)
class SynthOptions(Options):
    """Options of `synthesize`.

    Attributes:
        num_poses: number of poses K (at least 3, one per split; at most MAX_POSES).
        seed: seeds the poses and the 80/10/10 split.
        pca_components: PCA components of the predictor (its capacity).
        ridge: ridge penalty of the pose -> PCA-coefficient regression (bias unpenalized).
        garment: "shirt" (a T-shirt on a mannequin: torso, neck and upper arms) or "skirt"
            (a flared skirt on hips and legs whose hem swings and falls into flutes).
        body: write the wearer as the dataset's body; off, the garment alone.
    """

    num_poses: int = knob(300, "number of poses (one per split at least)", low=3, high=MAX_POSES)
    seed: int = knob(0, "seed of the poses, folds and split", low=0, high=MAX_SEED)
    pca_components: int = knob(6, "PCA components of the built-in predictor (its capacity)", low=1, high=1000,
                          flag=False)
    ridge: float = knob(1e-2, "ridge penalty of the predictor's regression from the pose", low=0, flag=False)
    garment: Literal["shirt", "skirt"] = knob("shirt", "shirt: a T-shirt on a mannequin; skirt: a flared skirt on "
                                              "hips and legs")
    body: bool = knob(True, "write the wearer as the dataset's body (--no-body: the garment alone)")
