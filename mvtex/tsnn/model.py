"""Texture sliding networks: -> (2, R, R) displacement image over the UV atlas.

`paper` (`TSNN`, the paper's architecture) maps the pose vector alone; `unet` (`UNet`, the
default) maps geometry images of the inferred mesh, optionally the camera's view of it, and
the pose. `build_network` makes either from config.json's "architecture".

The paper architecture:

    pose (P,) -> normalise (training mean/std) -> Linear -> BatchNorm + ReLU (+ dropout) -> (C0, S, S)
         -> depth x [ConvTranspose2d(4, stride 2) + BatchNorm2d + ReLU]   (S -> S * 2^depth = R)
         -> Conv2d 3x3 -> (2, R, R), times `output_scale`, plus a learned bias image

The paper's network maps a 1x1x90 pose to 512x512x4 (front and back images, two channels
each); here one image covers the whole atlas (all charts), two channels (du, dv). The
image follows the atlas convention of `mvtex.tsnn.atlas` (row 0 at v ≈ 0).

The bias image is initialised by the trainer with the mean training displacement, so the
layers learn the pose-dependent part only; the pose normalisation and the output unit are
buffers of the state dict, so a checkpoint is self-contained.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np
import torch
from torch import nn

from mvtex.tsnn.gp import GPConfig, PoseGP
from mvtex.tsnn.mlp import MLPConfig, PoseMLP


def _architecture_keys(cls, d: dict[str, Any]) -> dict[str, Any]:
    """An `architecture` dict without its "arch" key; ValueError naming keys `cls` lacks."""
    d = {k: v for k, v in d.items() if k != "arch"}
    unknown = set(d) - {f.name for f in fields(cls)}
    if unknown:
        raise ValueError(f"unknown architecture keys {sorted(unknown)}")
    return d


@dataclass(frozen=True)
class PaperConfig:
    """Architecture of a `TSNN`.

    Attributes:
        pose_dim: P, length of the pose vector.
        resolution: R, output image size (R x R); R / 2**depth must be a whole number >= 1.
        depth: number of upsampling stages (default: from a 4 x 4 start, log2(R / 4)).
        width: channels of the first stage; each later stage halves it, down to `min_width`.
        min_width: fewest channels of any stage.
        dropout: dropout probability on the pose embedding (output of the linear layer).
    """

    pose_dim: int
    resolution: int = 128
    depth: int | None = None
    width: int = 256
    min_width: int = 16
    dropout: float = 0.0

    @property
    def num_stages(self) -> int:
        if self.depth is not None:
            return int(self.depth)
        return int(round(math.log2(self.resolution / 4)))

    @property
    def start(self) -> int:
        return self.resolution // 2 ** self.num_stages

    def channels(self) -> list[int]:
        """Channels before each stage and after the last, (depth + 1) numbers."""
        return [max(self.min_width, self.width >> i) for i in range(self.num_stages + 1)]

    def validate(self) -> None:
        if self.pose_dim < 1:
            raise ValueError(f"pose_dim must be positive, got {self.pose_dim}")
        if self.num_stages < 1 or self.resolution % 2 ** self.num_stages or self.start < 1:
            raise ValueError(f"resolution {self.resolution} is not a multiple of 2**depth "
                             f"(depth {self.num_stages}); use a power of two such as 64, 128, 256 or 512")
        if self.width < 1 or self.min_width < 1:
            raise ValueError("width and min_width must be positive")

    def to_dict(self) -> dict[str, Any]:
        d = {"arch": "paper", **asdict(self)}
        d["depth"] = self.num_stages
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "PaperConfig":
        d = _architecture_keys(cls, d)
        config = cls(**{k: (None if d[k] is None else float(d[k]) if k == "dropout" else int(d[k])) for k in d})
        config.validate()
        return config


class TSNN(nn.Module):
    """Pose -> displacement image.

    Args:
        config: the architecture.

    Buffers (saved in the state dict): `pose_mean`, `pose_std` (P,) float32 normalisation of
    the input; `output_scale` () float32, the displacement unit the last layer works in.
    """

    pose_mean: torch.Tensor  # a buffer
    pose_std: torch.Tensor  # a buffer
    output_scale: torch.Tensor  # a buffer

    def __init__(self, config: PaperConfig):
        super().__init__()
        config.validate()
        self.config = config
        ch = config.channels()
        s = config.start
        self.register_buffer("pose_mean", torch.zeros(config.pose_dim))
        self.register_buffer("pose_std", torch.ones(config.pose_dim))
        self.register_buffer("output_scale", torch.tensor(1.0))
        self.fc = nn.Linear(config.pose_dim, ch[0] * s * s)
        self.fc_norm = nn.BatchNorm2d(ch[0])
        self.dropout = nn.Dropout(config.dropout)
        stages = []
        for cin, cout in zip(ch[:-1], ch[1:]):
            stages += [nn.ConvTranspose2d(cin, cout, kernel_size=4, stride=2, padding=1, bias=False),
                       nn.BatchNorm2d(cout), nn.ReLU(inplace=True)]
        self.stages = nn.Sequential(*stages)
        self.head = nn.Conv2d(ch[-1], 2, kernel_size=3, padding=1)
        nn.init.zeros_(self.head.bias)
        self.bias = nn.Parameter(torch.zeros(1, 2, config.resolution, config.resolution))

    def set_normalisation(self, pose_mean, pose_std, output_scale: float) -> None:
        """Store the input normalisation (training poses' mean and std) and the output unit."""
        std = torch.as_tensor(pose_std, dtype=torch.float32)
        self.pose_mean.copy_(torch.as_tensor(pose_mean, dtype=torch.float32))
        # A constant pose component carries no information; dividing by ~0 would amplify noise.
        self.pose_std.copy_(torch.where(std > 1e-8, std, torch.ones_like(std)))
        self.output_scale.fill_(float(output_scale))

    def forward(self, poses: torch.Tensor) -> torch.Tensor:
        """(B,P) raw pose vectors -> (B,2,R,R) displacement images (uv units)."""
        x = (poses - self.pose_mean) / self.pose_std
        s = self.config.start
        x = self.fc(x).view(x.shape[0], -1, s, s)
        x = self.dropout(torch.relu(self.fc_norm(x)))
        x = self.head(self.stages(x))
        return (x + self.bias) * self.output_scale


@dataclass(frozen=True)
class UNetConfig:
    """Architecture of a `UNet` (the default `unet` TSNN).

    Attributes:
        pose_dim: P, length of the pose vector (injected at the bottleneck).
        resolution: R, size of the input and output atlas images (R x R), a multiple of
            2**(len(widths) - 1).
        geometry_channels: channels of the geometry images (`mvtex.tsnn.geometry`).
        view: condition on a camera: per-texel positions and normals in camera coordinates
            and the cosine between normal and view ray are added as inputs (7 channels).
        widths: channels at each resolution level, from R down to R / 2**(levels-1).
    """

    pose_dim: int
    resolution: int = 64
    geometry_channels: int = 9
    view: bool = False
    widths: tuple[int, ...] = (8, 16, 32, 64)

    @property
    def view_channels(self) -> int:
        return 7 if self.view else 0

    def validate(self) -> None:
        if self.pose_dim < 1 or self.geometry_channels < 6:
            raise ValueError("pose_dim must be positive and geometry_channels at least 6 (positions, normals)")
        if len(self.widths) < 2 or min(self.widths) < 1:
            raise ValueError(f"widths must hold at least two positive numbers, got {self.widths}")
        if self.resolution < 2 ** len(self.widths) or self.resolution % 2 ** (len(self.widths) - 1):
            raise ValueError(f"resolution {self.resolution} is not a multiple of 2**{len(self.widths) - 1} "
                             "(one halving per level); use a power of two such as 32, 64 or 128")

    def to_dict(self) -> dict[str, Any]:
        return {"arch": "unet", **asdict(self), "widths": list(self.widths)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "UNetConfig":
        d = _architecture_keys(cls, d)
        if "widths" in d:
            if not isinstance(d["widths"], (list, tuple)):
                raise ValueError("widths must be a list of integers")
            d["widths"] = tuple(int(w) for w in d["widths"])
        if "view" in d and not isinstance(d["view"], bool):
            raise ValueError("view must be true or false")
        config = cls(**{k: (v if k in ("widths", "view") else int(v)) for k, v in d.items()})
        config.validate()
        return config


def _conv_block(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=False),
                         nn.GroupNorm(min(8, cout // 4) or 1, cout), nn.ReLU(inplace=True),
                         nn.Conv2d(cout, cout, 3, padding=1, bias=False),
                         nn.GroupNorm(min(8, cout // 4) or 1, cout), nn.ReLU(inplace=True))


class UNet(nn.Module):
    """Geometry images of X_N (+ the view, + the pose) -> displacement image.

        inputs (B, G [+7 view] + 3, R, R): normalised geometry images, the camera-frame view
               channels when `view`, the chart mask and the texel's (u, v)
        -> encoder: per level two 3x3 conv + GroupNorm + ReLU, stride 2 between levels
        -> bottleneck + Linear(normalised pose) reshaped to the bottleneck's size
        -> decoder: bilinear x2, concatenate the encoder's level, two 3x3 convs
        -> 1x1 conv -> (2, R, R), times `output_scale`, plus a learned bias image

    Buffers (saved in the state dict): `pose_mean`, `pose_std` (P,); `geometry_mean`,
    `geometry_std` (G,); `view_mean`, `view_std` (7,); `atlas` (3,R,R) chart mask (dilated)
    and texel-centre (u, v); `output_scale` ().

    Args:
        config: the architecture.
    """

    pose_mean: torch.Tensor  # a buffer
    pose_std: torch.Tensor  # a buffer
    geometry_mean: torch.Tensor  # a buffer
    geometry_std: torch.Tensor  # a buffer
    view_mean: torch.Tensor  # a buffer
    view_std: torch.Tensor  # a buffer
    atlas: torch.Tensor  # a buffer
    output_scale: torch.Tensor  # a buffer

    def __init__(self, config: UNetConfig):
        super().__init__()
        config.validate()
        self.config = config
        r, w = config.resolution, config.widths
        self.register_buffer("pose_mean", torch.zeros(config.pose_dim))
        self.register_buffer("pose_std", torch.ones(config.pose_dim))
        self.register_buffer("geometry_mean", torch.zeros(config.geometry_channels))
        self.register_buffer("geometry_std", torch.ones(config.geometry_channels))
        self.register_buffer("view_mean", torch.zeros(7))
        self.register_buffer("view_std", torch.ones(7))
        self.register_buffer("atlas", torch.zeros(3, r, r))
        self.register_buffer("output_scale", torch.tensor(1.0))
        cin = config.geometry_channels + config.view_channels + 3
        self.down = nn.ModuleList()
        for i, width in enumerate(w):
            self.down.append(_conv_block(cin, width, stride=1 if i == 0 else 2))
            cin = width
        bottom = r // 2 ** (len(w) - 1)
        self.pose_fc = nn.Linear(config.pose_dim, w[-1] * bottom * bottom)
        self.up = nn.ModuleList(_conv_block(w[i + 1] + w[i], w[i]) for i in reversed(range(len(w) - 1)))
        self.head = nn.Conv2d(w[0], 2, 1)
        with torch.no_grad():
            self.head.weight.mul_(0.1)  # start close to the bias image (the mean displacement)
        nn.init.zeros_(self.head.bias)
        self.bias = nn.Parameter(torch.zeros(1, 2, r, r))

    def set_normalisation(self, *, pose_mean, pose_std, geometry_mean, geometry_std, view_mean=None, view_std=None,
                          atlas, output_scale: float) -> None:
        """Store input statistics (training data), the atlas channels and the output unit."""
        def std(value):
            # A constant input carries no information; dividing by ~0 would amplify noise.
            value = torch.as_tensor(np.asarray(value), dtype=torch.float32)
            return torch.where(value > 1e-8, value, torch.ones_like(value))

        self.pose_mean.copy_(torch.as_tensor(np.asarray(pose_mean), dtype=torch.float32))
        self.pose_std.copy_(std(pose_std))
        self.geometry_mean.copy_(torch.as_tensor(np.asarray(geometry_mean), dtype=torch.float32))
        self.geometry_std.copy_(std(geometry_std))
        if view_mean is not None:
            self.view_mean.copy_(torch.as_tensor(np.asarray(view_mean), dtype=torch.float32))
            self.view_std.copy_(std(view_std))
        self.atlas.copy_(torch.as_tensor(np.asarray(atlas), dtype=torch.float32))
        self.output_scale.fill_(float(output_scale))

    @staticmethod
    def view_features(geometry: torch.Tensor, cam_from_world: torch.Tensor) -> torch.Tensor:
        """Per-texel view of raw geometry images from cameras.

        Args:
            geometry: (B,G,R,R) raw geometry images (channels 0-2 positions, 3-5 normals).
            cam_from_world: (B,3,4) extrinsics [R | t] (x_cam = R x_world + t).

        Returns:
            (B,7,R,R): positions (3) and normals (3) in camera coordinates, and
            -cos(normal, view ray) (1; 1 = the surface faces the camera).
        """
        rot, t = cam_from_world[:, :, :3], cam_from_world[:, :, 3]
        pos = torch.einsum("bij,bjhw->bihw", rot, geometry[:, 0:3]) + t[:, :, None, None]
        nrm = torch.einsum("bij,bjhw->bihw", rot, geometry[:, 3:6])
        ray = pos / pos.norm(dim=1, keepdim=True).clamp_min(1e-9)
        facing = -(ray * nrm).sum(1, keepdim=True)
        return torch.cat([pos, nrm, facing], dim=1)

    def forward(self, poses: torch.Tensor, geometry: torch.Tensor, cam_from_world: torch.Tensor | None = None):
        """Displacement images.

        Args:
            poses: (B,P) raw pose vectors.
            geometry: (B,G,R,R) raw geometry images of the poses' inferred meshes.
            cam_from_world: (B,3,4) camera extrinsics; required when `config.view`.

        Returns:
            (B,2,R,R) displacement images (uv units).
        """
        mask = self.atlas[0:1][None]
        x = (geometry - self.geometry_mean[None, :, None, None]) / self.geometry_std[None, :, None, None]
        parts = [x]
        if self.config.view:
            if cam_from_world is None:
                raise ValueError("this network is conditioned on a camera: pass cam_from_world")
            v = self.view_features(geometry, cam_from_world)
            parts.append((v - self.view_mean[None, :, None, None]) / self.view_std[None, :, None, None])
        x = torch.cat(parts, dim=1) * mask
        x = torch.cat([x, self.atlas[None].expand(x.shape[0], -1, -1, -1)], dim=1)
        skips = []
        for i, block in enumerate(self.down):
            x = block(x)
            skips.append(x)
        p = (poses - self.pose_mean) / self.pose_std
        x = x + self.pose_fc(p).view(x.shape)
        for block, skip in zip(self.up, reversed(skips[:-1])):
            x = torch.nn.functional.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            x = block(torch.cat([x, skip], dim=1))
        return (self.head(x) + self.bias) * self.output_scale


def build_network(arch: dict[str, Any]) -> nn.Module:
    """The model an `architecture` dict of config.json describes ("arch": "paper", "unet" or
    "gp"; no "arch" key: "paper", as written by the first model version).

    Raises:
        ValueError: unknown arch or keys, or an invalid configuration.
    """
    kind = arch.get("arch", "paper")
    if kind == "paper":
        return TSNN(PaperConfig.from_dict({k: v for k, v in arch.items() if k != "arch"}))
    if kind == "unet":
        return UNet(UNetConfig.from_dict(arch))
    if kind == "gp":

        return PoseGP(GPConfig.from_dict(arch))
    if kind == "mlp":

        return PoseMLP(MLPConfig.from_dict(arch))
    raise ValueError(f"unknown arch {kind!r} (paper, unet, gp or mlp)")
