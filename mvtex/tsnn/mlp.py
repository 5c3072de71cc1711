"""Pose -> per-vertex displacements by an ensemble of small MLPs on a PCA basis (`--arch mlp`).

The same representation as `gp` (mvtex.tsnn.pca): d of one camera is the mean plus the
first C principal components of the training displacements,

    d(θ) = mean + Σ_c f_c(θ) · basis_c,

but the coefficients f(θ) (C,) come from E multilayer perceptrons (standardised pose ->
two hidden layers of H SiLU units -> C), trained independently (their own initialisation
and batch order) and averaged. The loss is the mean squared error of the coefficients in
uv units, which, the basis being orthonormal, is the squared error of d within the span
of the basis. Each member keeps the weights of its epoch with the lowest validation loss.
An MLP costs O(K) per epoch where an exact GP costs O(K³): it is the model for training
sets of thousands of poses. The members' spread is a predictive uncertainty:
`PoseMLP.member_displacements` gives every member's d, and `PoseMLP.predictive_std` the
per-vertex standard deviation of d over the members.

It is an `nn.Module` whose state is plain tensors, so a model directory stores it like the
networks (model.safetensors + config.json "architecture": {"arch": "mlp", ...}).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch
from torch import nn

from mvtex.tsnn.modeldir import IntegerConfig
from mvtex.tsnn.pca import pose_pca_counted

MAX_MEMBERS = 32


MAX_HIDDEN = 4096


MAX_COMPONENTS = 256


# Optimiser steps of a fit (at least one epoch, at most MAX_EPOCHS epochs): on small
# training sets many epochs, on large ones a few hundred.
STEPS = 4000


MAX_EPOCHS = 1000


BATCH = 128


@dataclass(frozen=True)
class MLPConfig(IntegerConfig):
    """Shape of a `PoseMLP`.

    Attributes:
        pose_dim: P, length of the pose vector.
        num_vertices: n', vertices the displacements are predicted at.
        components: C, principal components of d predicted.
        hidden: H, units of each of the two hidden layers.
        members: E, networks averaged.
    """

    ARCH = "mlp"

    pose_dim: int
    num_vertices: int
    components: int
    hidden: int = 128
    members: int = 5

    def validate(self) -> None:
        if self.pose_dim < 1 or self.num_vertices < 1:
            raise ValueError("pose_dim and num_vertices must be positive")
        if not 0 <= self.components <= MAX_COMPONENTS:
            raise ValueError(f"components must be in 0..{MAX_COMPONENTS}, got {self.components}")
        if not 1 <= self.hidden <= MAX_HIDDEN or not 1 <= self.members <= MAX_MEMBERS:
            raise ValueError(f"hidden must be in 1..{MAX_HIDDEN} and members in 1..{MAX_MEMBERS}, "
                             f"got {self.hidden} and {self.members}")



class PoseMLP(nn.Module):
    """An ensemble of MLPs on the principal components of d: pose (B,P) -> d (B,n',2) float32.

    Parameters (E members stacked, float32): w1 (E,P,H), b1 (E,1,H), w2 (E,H,H), b2 (E,1,H),
    w3 (E,H,C), b3 (E,1,C). Buffers: pose_mean/pose_std (P,), basis (C,2n') orthonormal rows,
    mean (2n',), output_scale () the uv scale of the coefficients the members output.
    """

    pose_mean: torch.Tensor  # a buffer
    pose_std: torch.Tensor  # a buffer
    basis: torch.Tensor  # a buffer
    mean: torch.Tensor  # a buffer
    output_scale: torch.Tensor  # a buffer

    per_vertex = True  # predicts d at the vertices, not an atlas image

    def __init__(self, config: MLPConfig):
        super().__init__()
        config.validate()
        self.config = config
        e, p, h, c, n = config.members, config.pose_dim, config.hidden, config.components, config.num_vertices
        self.w1 = nn.Parameter(torch.zeros(e, p, h))
        self.b1 = nn.Parameter(torch.zeros(e, 1, h))
        self.w2 = nn.Parameter(torch.zeros(e, h, h))
        self.b2 = nn.Parameter(torch.zeros(e, 1, h))
        self.w3 = nn.Parameter(torch.zeros(e, h, c))
        self.b3 = nn.Parameter(torch.zeros(e, 1, c))
        self.register_buffer("pose_mean", torch.zeros(p))
        self.register_buffer("pose_std", torch.ones(p))
        self.register_buffer("basis", torch.zeros(c, 2 * n))
        self.register_buffer("mean", torch.zeros(2 * n))
        self.register_buffer("output_scale", torch.tensor(1.0))

    def initialise(self, generator: torch.Generator) -> None:
        """He-uniform weights and zero biases, every member its own draw."""
        with torch.no_grad():
            for w in (self.w1, self.w2, self.w3):
                bound = math.sqrt(6.0 / w.shape[1]) * (1.0 if w is not self.w3 else 0.1)
                w.copy_((torch.rand(w.shape, generator=generator) * 2 - 1) * bound)
            for b in (self.b1, self.b2, self.b3):
                b.zero_()

    def coefficients(self, z: torch.Tensor) -> torch.Tensor:
        """Every member's coefficients (E,B,C), in units of `output_scale`, of standardised poses z (B,P)."""
        x = z.to(self.w1.dtype).expand(self.config.members, -1, -1)
        h = nn.functional.silu(torch.baddbmm(self.b1, x, self.w1))
        h = nn.functional.silu(torch.baddbmm(self.b2, h, self.w2))
        return torch.baddbmm(self.b3, h, self.w3)

    def _standardise(self, poses: torch.Tensor) -> torch.Tensor:
        return (poses.to(torch.float32) - self.pose_mean) / self.pose_std

    def member_displacements(self, poses: torch.Tensor) -> torch.Tensor:
        """d of every member, (E,B,n',2) float32."""
        coef = self.coefficients(self._standardise(poses)) * self.output_scale
        return (self.mean + coef @ self.basis).reshape(self.config.members, len(poses), -1, 2)

    def forward(self, poses: torch.Tensor) -> torch.Tensor:
        coef = self.coefficients(self._standardise(poses)).mean(0) * self.output_scale
        return (self.mean + coef @ self.basis).reshape(len(poses), -1, 2)

    def predictive_std(self, poses: torch.Tensor) -> torch.Tensor:
        """Per-vertex spread of the members, (B,n') float32: sqrt of the mean over members of
        ‖d_e - d̄‖² (uv units)."""
        coef = self.coefficients(self._standardise(poses)) * self.output_scale  # (E,B,C)
        dev = (coef - coef.mean(0)) @ self.basis  # (E,B,2n')
        return dev.reshape(self.config.members, len(poses), -1, 2).square().sum(-1).mean(0).sqrt()


def fit_pose_mlp(poses: np.ndarray, d, val_poses: np.ndarray, val_d: np.ndarray, components: int = 64,
                 hidden: int = 128, members: int = 5, seed: int = 0, lr: float = 1e-3, weight_decay: float = 1e-4,
                 progress: Callable[[int, int], None] | None = None, threads: int = 1,
                 steps: int | None = None) -> tuple[PoseMLP, dict]:
    """Fit a `PoseMLP` to training displacements, choosing each member's epoch on validation poses.

    Args:
        poses: (K,P) training pose vectors.
        d: (K,n',2) their displacements, an array or anything `d[rows]` reads rows of.
        val_poses: (V,P) validation pose vectors (V >= 1); val_d: (V,n',2) their displacements.
        components: principal components of d predicted (fewer when K - 1 is smaller).
        hidden, members: see `MLPConfig`.
        seed: seeds the initialisation and the batch order of every member.
        lr: AdamW learning rate (cosine decay to 5 % over the fit); weight_decay: AdamW's.
        progress: called with (steps done, steps): the chunks of training poses read
            (`mvtex.tsnn.pca.pose_pca`), then one step per epoch.
        threads: torch threads of the fit. The steps are small: on a shared 2-core machine
            two threads ran a fit 7 times slower than one (per-operation barriers).
        steps: optimiser steps (None: `STEPS`); at least one epoch, at most `MAX_EPOCHS`.

    Returns:
        (the model in eval mode, history {"train": [...], "val": [...]}: per epoch, the mean
        over members of the squared error of d per vertex (uv², the sum over its two
        coordinates, within the basis), plus "best_epoch": [...] per member).
    """

    (x, mean_x, std_x, mean_d, basis, coef), reads = pose_pca_counted(poses, d, components, progress)
    k, p = x.shape
    if k < 2:
        raise ValueError(f"an mlp needs at least 2 training poses, got {k}")
    config = MLPConfig(pose_dim=p, num_vertices=len(mean_d) // 2, components=len(basis), hidden=hidden,
                       members=members)
    model = PoseMLP(config)
    generator = torch.Generator().manual_seed(seed)
    model.initialise(generator)
    val_flat = np.asarray(val_d, dtype=np.float64).reshape(len(val_d), -1) - mean_d
    val_coef = val_flat @ basis.T
    scale = float(np.sqrt(np.mean(coef ** 2))) if coef.size else 1.0
    scale = scale if scale > 0 else 1.0
    with torch.no_grad():
        model.pose_mean.copy_(torch.from_numpy(mean_x))
        model.pose_std.copy_(torch.from_numpy(std_x))
        model.basis.copy_(torch.from_numpy(basis))
        model.mean.copy_(torch.from_numpy(mean_d))
        model.output_scale.fill_(scale)
    z = torch.from_numpy(((x - mean_x) / std_x).astype(np.float32))
    y = torch.from_numpy((coef / scale).astype(np.float32))
    zv = torch.from_numpy(((np.asarray(val_poses, np.float64) - mean_x) / std_x).astype(np.float32))
    yv = torch.from_numpy((val_coef / scale).astype(np.float32))
    batch = min(BATCH, k)
    per_epoch = max(1, k // batch)
    epochs = int(min(MAX_EPOCHS, max(1, math.ceil((STEPS if steps is None else steps) / per_epoch))))
    params = list(model.parameters())
    optimiser = torch.optim.AdamW(params, lr=lr, weight_decay=weight_decay)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, T_max=epochs * per_epoch, eta_min=lr * 0.05)
    best_loss = torch.full((members,), math.inf)
    best_epoch = [0] * members
    best = [q.detach().clone() for q in params]
    history: dict[str, list] = {"train": [], "val": []}
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        for epoch in range(1, epochs + 1):
            model.train()
            # Each member its own batch order: (E,K) permutations.
            order = torch.argsort(torch.rand(members, k, generator=generator), dim=1)
            total = 0.0
            for s in range(per_epoch):
                idx = order[:, s * batch:(s + 1) * batch]  # (E,b)
                zb = z[idx]  # (E,b,P)
                h = nn.functional.silu(torch.baddbmm(model.b1, zb, model.w1))
                h = nn.functional.silu(torch.baddbmm(model.b2, h, model.w2))
                out = torch.baddbmm(model.b3, h, model.w3)
                loss = (out - y[idx]).square().sum(-1).mean(1)  # (E,)
                optimiser.zero_grad(set_to_none=True)
                loss.sum().backward()
                optimiser.step()
                schedule.step()
                total += float(loss.detach().mean())
            model.eval()
            with torch.no_grad():
                val = (model.coefficients(zv) - yv).square().sum(-1).mean(1)  # (E,)
                better = val < best_loss
                for e in torch.nonzero(better)[:, 0].tolist():
                    best_epoch[e] = epoch
                    for q, b in zip(params, best):
                        b[e].copy_(q[e])
                best_loss = torch.where(better, val, best_loss)
            # Per vertex: the squared error of the coefficients is that of d summed over its
            # 2n' coordinates (within the basis); divided by n' it is the networks' per-vertex MSE.
            history["train"].append(total / per_epoch * scale ** 2 / config.num_vertices)
            history["val"].append(float(val.mean()) * scale ** 2 / config.num_vertices)
            if progress is not None:
                progress(reads + epoch, reads + epochs)
    finally:
        torch.set_num_threads(previous)
    with torch.no_grad():
        for q, b in zip(params, best):
            q.copy_(b)
    history["best_epoch"] = best_epoch
    model.eval()
    return model, history
