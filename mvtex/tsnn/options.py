"""The options of training (`TrainOptions`), recorded in every model directory."""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Literal

from mvtex.util.checks import MAX_SEED
from mvtex.util.errors import OptionError
from mvtex.util.options import Options, knob

ARCHS = ("gp", "mlp", "unet", "paper")


MAX_RESOLUTION = 2048  # atlas image size: 2·R² floats per pose and per batch item


MAX_WIDTH = 1024  # channels of the first stage


MAX_COMPONENTS = 256  # principal components of d that gp and mlp model


MAX_MEMBERS = 32  # networks of an mlp ensemble


_DEVICE = re.compile(r"^(auto|cpu|mps|cuda(:\d{1,3})?)$")


@dataclass(frozen=True)
class TrainOptions(Options):
    """Options of `train`.

    Attributes:
        arch: "gp" (Gaussian processes of the pose on the principal components of d; one
            camera), "mlp" (an ensemble of MLPs of the pose on the same components; one
            camera), "unet" (geometry images of X_N + pose, a U-Net; the only one that
            conditions on the camera) or "paper" (pose only; one camera). None: "gp" for
            one camera, "unet" for all cameras. On the built-in garment's test poses `gp` is
            the most accurate at every size measured, 120 to 960 training poses (README,
            benchmarks/tsnn_learning_curve.py).
        components: principal components of d that `gp` (each its own GP) and `mlp` model.
        widths: channels per U-Net level (None: (8, 16, 32, 64)).
        epochs: most passes over the training poses.
        resolution: atlas image size R; None: 64 on CPU, 512 on CUDA. d is smooth over the
            atlas, and on the built-in shirt 64² generalises as well as 128² (test MSE of d
            1.11e-5 vs 1.13e-5) at about 0.6x the training time.
        batch_size: samples ((pose, camera) pairs) per optimiser step (None: 16 for `paper`,
            8 for `unet`, which learns per step and is cheap per sample).
        lr: Adam learning rate (the paper's 1e-3).
        device: "cpu", "cuda", "cuda:1", ... or "auto" (CUDA when available).
        seed: seeds weight initialisation and batch order.
        patience: stop after this many epochs without a better validation loss.
        weight_assigned: loss weight of vertices whose d came from the ray (unassigned,
            extrapolated vertices weigh 1); above 1 favours what the camera sees.
        width: channels of the first decoder stage of `paper` (None: 256 on CPU and CUDA);
            hidden units of each layer of an `mlp` member (None: 128).
        min_width: fewest channels of any decoder stage (None: 8 on CPU, 16 on CUDA).
        lr_min_factor: the learning rate decays along a cosine from lr to lr * this factor
            over `epochs` (1.0: constant).
        dilation: texels each chart is extended by in atlas images (see AtlasSampler).
        deterministic: use deterministic algorithms (always on CPU; on CUDA the bilinear
            sampling backward has no deterministic kernel, so it is off there by default).
        weight_decay: decoupled weight decay (AdamW) on all parameters (0: the paper's plain Adam).
        pose_noise: std of Gaussian noise added to training poses, in units of each pose
            component's training std (augmentation; 0: off).
        dropout: dropout probability on the pose embedding (the first stage's input; 0: off).
        members: networks of an `mlp` ensemble (its hidden layers have `width` units, its
            outputs are `components` principal components of d).
        gain: multiply every prediction by the gain in [0, 1] that minimises the loss on the
            validation poses (least squares; recorded in config.json): a model that learned
            little of d is shrunk towards no sliding (the inferred mesh's own texture
            coordinates). None: on for a corrected set (`mvtex correct`), where what the
            corrector left is mostly not a function of the pose (on the validation poses of
            both built-in garments at 160 and 240 training poses, `gp` models explain
            -8 % to 12 % of it, and their fitted gains are 0-0.97), off otherwise (the same
            models on the original sets explain 59-66 %, gains 0.97-1.10).
    """

    arch: Literal["gp", "mlp", "unet", "paper"] | None = knob(
        None, "gp: Gaussian processes of the pose on the principal components of d, per camera; mlp: an ensemble "
        "of MLPs of the pose on the same components, per camera; unet: geometry images of the inferred mesh + pose, "
        "any camera; paper: the paper's pose-only decoder, per camera",
        auto="gp with --cameras, unet without")
    components: int = knob(32, "principal components of d that gp and mlp model (with --geometry: of gt - inferred)", low=1, high=MAX_COMPONENTS)
    widths: tuple[int, ...] | None = knob(None, "channels per U-Net level, comma-separated", low=1,
                                          auto="8,16,32,64", metavar="A,B,...")
    epochs: int = knob(60, "most training epochs of unet, paper and mlp", low=1)
    resolution: int | None = knob(None, "atlas image size of unet and paper, a power of two", low=8,
                                  high=MAX_RESOLUTION, auto="64 on CPU, 256 or 512 on CUDA")
    batch_size: int | None = knob(None, "samples per optimiser step", low=1, auto="16 for paper, 8 for unet")
    lr: float = knob(1e-3, "Adam learning rate", low=0, low_open=True)
    device: str = knob("auto", "cpu, cuda, cuda:N, mps or auto (CUDA when available)")
    seed: int = knob(0, "seed of initialisation and batch order", low=0, high=MAX_SEED)
    patience: int = knob(15, "stop after this many epochs without a better validation loss", low=1)
    weight_assigned: float = knob(1.0, "loss weight of vertices whose d came from the ray (filled ones weigh 1)",
                                  low=0, low_open=True)
    width: int | None = knob(None, "channels of paper's first stage; hidden units of an mlp member", low=1,
                             high=MAX_WIDTH, auto="256 for paper, 128 for mlp")
    min_width: int | None = knob(None, "fewest channels of any decoder stage", low=1, high=MAX_WIDTH,
                                 auto="8 on CPU, 16 on CUDA")
    lr_min_factor: float = knob(0.05, "the learning rate decays along a cosine to lr times this", low=0, high=1,
                                low_open=True)
    dilation: int = knob(2, "texels each chart is extended by in atlas images", low=0, high=64)
    deterministic: bool | None = knob(None, "deterministic algorithms", auto="on for CPU, off for CUDA")
    weight_decay: float = knob(0.0, "decoupled weight decay (AdamW)", low=0)
    pose_noise: float = knob(0.0, "std of noise added to training poses, in units of each pose coordinate's std",
                             low=0)
    dropout: float = knob(0.0, "dropout probability on the pose embedding", low=0, high=1, high_open=True)
    members: int = knob(5, "networks of an mlp ensemble", low=1, high=MAX_MEMBERS)
    gain: bool | None = knob(None, "multiply predictions by the gain in [0, 1] fitted on the validation poses, "
                             "which shrinks a model that learned little towards no sliding",
                             auto="on for a corrected set (mvtex correct), off otherwise")

    def validate(self) -> None:
        if not _DEVICE.match(self.device):
            raise OptionError("device", f"must be auto, cpu, mps, cuda or cuda:N, got {self.device!r}")
        if self.resolution is not None and self.resolution & (self.resolution - 1):
            raise OptionError("resolution", f"must be a power of two in 8..{MAX_RESOLUTION}, got {self.resolution}")
        if self.arch == "unet" and self.resolution is not None:  # one halving per level
            levels = len(self.widths) if self.widths else 4
            if self.resolution < 2 ** levels:
                raise OptionError("resolution", f"must be at least {2 ** levels} for the unet ({levels} levels), "
                                  f"got {self.resolution}")


@dataclass(frozen=True)
class GeometryOptions(Options):
    """Options of `train_geometry` (`mvtex train --geometry`).

    Attributes:
        components: principal components of the residual gt - inferred modelled, each by
            its own GP (fewer when the training poses are fewer). 32: on the validation
            poses of both built-in garments (240 training poses) 16, 64 and 128 give the
            same RMSE within 0.5 %, 8 is 4-9 % worse.
        iterations: most L-BFGS iterations of each component's hyperparameters. 20 (`gp`
            takes 40): on the validation poses of both built-in garments (240 training
            poses) the corrected mesh's RMSE is 0.4 % above 40 iterations' on the T-shirt and
            1.8 % below on the skirt, and the fit costs 25-40 % less.
        device: "cpu", "cuda", "cuda:N", "mps" or "auto" (CUDA when available): where the
            likelihoods are evaluated; the model is the same up to rounding.
    """

    components: int = knob(32, "principal components of the residual gt - inferred that the corrector models",
                           low=1, high=MAX_COMPONENTS)
    iterations: int = knob(20, "with --geometry: most L-BFGS iterations of each component's hyperparameters",
                           low=1, high=1000)
    device: str = knob("auto", "cpu, cuda, cuda:N, mps or auto (CUDA when available)")

    def validate(self) -> None:
        if not _DEVICE.match(self.device):
            raise OptionError("device", f"must be auto, cpu, mps, cuda or cuda:N, got {self.device!r}")


@dataclass(frozen=True)
class CorrectOptions(Options):
    """Options of `correct` (`mvtex correct`).

    Attributes:
        shrink: κ ≥ 0: each vertex keeps f = ‖r‖² / (‖r‖² + κσ²) of its predicted residual
            r (σ its predictive standard deviation): where the corrector's σ is large
            against the correction it makes, the mesh stays nearer the predictor's. 0: the
            whole correction. The default 0.25 was chosen on the validation poses of both
            built-in garments (240 training poses; docs/tsnn.md): the worst pose's ratio
            there rises from 0.93 to 1.03 (T-shirt) and from 0.72 to 0.79 (skirt), the
            median falls by 1.2 % and 0 %, the mean RMSE grows by 0.7 % and 2.5 %.
    """

    shrink: float = knob(0.25, "keep |r|2/(|r|2 + K sigma2) of each vertex's correction r, sigma its uncertainty; "
                         "0 keeps all of it", low=0, metavar="K")
