"""The options of calibration (`CalibrateOptions`)."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Literal

from mvtex.calibration.board import BoardSpec
from mvtex.util.checks import check_instance
from mvtex.util.options import NO_DEFAULT, Options, knob

DISTORTION_MODELS = ("k1k2p1p2k3", "k1k2p1p2", "k1k2", "none")


@dataclass(frozen=True)
class CalibrateOptions(Options):
    """Options of `calibrate` (the `mvtex calibrate` flags are made from them).

    Attributes:
        board: the board in the images.
        reference: camera whose frame is the rig's world frame (default: first by name).
        min_corners: frames where a camera sees fewer corners are skipped.
        distortion: the distortion coefficients to fit (OpenCV's k1, k2, p1, p2, k3; the
            others stay 0): "k1k2p1p2k3", "k1k2p1p2" (the default: k3 is poorly
            determined unless the lens is wide), "k1k2" or "none" (pinhole).
        huber_px: residual (pixels) above which the bundle adjustment down-weights a corner.
    """

    board: BoardSpec = knob(NO_DEFAULT, "the board in the images", flag=False)
    reference: str | None = knob(None, "camera whose frame is the rig's world frame", auto="the first by name")
    min_corners: int = knob(6, "skip frames where a camera sees fewer corners", low=4)
    distortion: Literal["k1k2p1p2k3", "k1k2p1p2", "k1k2", "none"] = knob(
        "k1k2p1p2", "distortion coefficients to fit (none: pinhole)")
    huber_px: float = knob(1.0, "residual above which the bundle adjustment down-weights a corner", unit="px",
                           low=0, low_open=True)

    def validate(self) -> None:
        check_instance(self.board, BoardSpec, "board")

    def to_json(self) -> dict:
        out = asdict(self)
        out["board"] = str(self.board)
        return out
