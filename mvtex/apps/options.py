"""The options of the demo (`DemoOptions`)."""

from __future__ import annotations

from dataclasses import dataclass

from mvtex.synth.options import MAX_POSES
from mvtex.util.checks import MAX_SEED
from mvtex.util.options import Options, knob

MIN_POSES = 10  # the test split must hold a pose to show, the training split enough for a model


@dataclass(frozen=True)
class DemoOptions(Options):
    """Options of `run_demo`.

    Attributes:
        num_poses: poses of the built-in dataset (at least `MIN_POSES`).
        seed: seed of the dataset.
        tsnn: also train and evaluate the per-camera model.
    """

    num_poses: int = knob(120, "poses of the built-in dataset to synthesize", low=MIN_POSES, high=MAX_POSES)
    seed: int = knob(0, "seed of the built-in dataset", low=0, high=MAX_SEED)
    tsnn: bool = knob(True, "also train the per-camera models and run the learned stages", flag=False)
