"""The texture sliding network: pose vector -> (2, R, R) displacement image over the UV atlas.

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

import torch
from torch import nn


@dataclass(frozen=True)
class ModelConfig:
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
        d = asdict(self)
        d["depth"] = self.num_stages
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "ModelConfig":
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown architecture keys {sorted(unknown)}")
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

    def __init__(self, config: ModelConfig):
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
