"""Pose -> per-vertex displacements by Gaussian processes on a PCA basis (`--arch gp`).

A few hundred simulated poses are too few for a convolutional decoder to learn d from the
pose (docs/results/accuracy.md, the TSNN learning curve), but d of one camera is a smooth function of the pose
dominated by a few modes: how far material rides around and along the body, which folds are
on. So:

    d(θ) = mean + Σ_c f_c(θ) · basis_c          basis: the first C principal components of
                                                the training displacements (K, 2n')
    f_c  ~ GP(0, k_c) + noise σ_c²                                      on standardised θ
    k_c(θ, θ') = s_c² exp(-½ Σ_i r_i²) + t_c² Σ_i exp(-½ r_i²),   r_i = (θ_i - θ'_i) / ℓ_ci

The first term is the usual squared-exponential kernel with automatic-relevance
lengthscales; the second, additive term (a sum of one-dimensional squared exponentials)
carries what each pose coordinate does on its own, which a few hundred poses in a dozen
dimensions pin down far better than the interactions (on the built-in shirt, same-chart
ratio at 240 training poses 2.09 -> 2.26). Every component has its own lengthscales ℓ_c,
s_c, t_c and noise, chosen by maximising the log marginal likelihood (L-BFGS,
deterministic on the CPU); prediction is the posterior mean k_c(θ, Θ) α_c with
α_c = (K_c + σ_c² I)⁻¹ y_c. Nothing is learned per texel, so it needs no atlas: it reads
and writes d at the vertices. The exact GP costs O(K³) in the number of training poses, so
at most `MAX_TRAIN` (evenly spaced) training poses are used; beyond that the networks have
the data they need.

It is an `nn.Module` with buffers only, so a model directory stores it like the networks
(model.safetensors + config.json "architecture": {"arch": "gp", ...}).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any, Callable

import numpy as np
import torch
from torch import nn

MAX_TRAIN = 2000  # training poses an exact GP is fitted on (O(K^3) time, O(K^2) memory)


MAX_COMPONENTS = 256


HYPER_POSES = 400  # training poses the hyperparameters are fitted on, before refining on all


_REFINE_ITERATIONS = 100  # on the shirt at 960 poses: 30 -> same-chart ratio 2.998, 100 -> 3.02


_REFINE_ELEMENTS = 2e7  # refinement poses K' with K'^2 P below this (the additive kernel's autograd memory)


# (lengthscale, noise std, log std of the additive part) starts, standardised units
_STARTS = ((1.0, 0.1, -2.0), (4.0, 0.1, -2.0), (1.0, 0.5, 0.0))


# Shortest lengthscale, in training standard deviations of the pose coordinate: shorter ones
# only fit noise (a few hundred poses cannot resolve them in a dozen dimensions).
_LOG_L_MIN = math.log(0.3)


@dataclass(frozen=True)
class GPConfig:
    """Shape of a `PoseGP`.

    Attributes:
        pose_dim: P, length of the pose vector.
        num_vertices: n', vertices the displacements are predicted at.
        num_train: K, training poses the GP conditions on.
        components: C, principal components of d modelled (each by its own GP).
    """

    pose_dim: int
    num_vertices: int
    num_train: int
    components: int

    def validate(self) -> None:
        if self.pose_dim < 1 or self.num_vertices < 1 or self.num_train < 1:
            raise ValueError("pose_dim, num_vertices and num_train must be positive")
        if not 0 <= self.components <= min(MAX_COMPONENTS, self.num_train):
            raise ValueError(f"components must be in 0..min({MAX_COMPONENTS}, num_train), got {self.components}")
        if self.num_train > MAX_TRAIN:
            raise ValueError(f"num_train is at most {MAX_TRAIN}, got {self.num_train}")

    def to_dict(self) -> dict[str, Any]:
        return {"arch": "gp", **asdict(self)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "GPConfig":
        d = {k: v for k, v in d.items() if k != "arch"}
        unknown = set(d) - {f.name for f in fields(cls)}
        if unknown:
            raise ValueError(f"unknown architecture keys {sorted(unknown)}")
        if any(isinstance(v, bool) or not isinstance(v, int) for v in d.values()):
            raise ValueError("gp architecture values must be integers")
        config = cls(**d)
        config.validate()
        return config


class PoseGP(nn.Module):
    """Posterior mean of per-component GPs: pose (B,P) -> d (B,n',2), float32.

    Buffers (float64): pose_mean/pose_std (P,), inputs (K,P) standardised training poses,
    log_lengthscale (C,P), log_signal (C,), log_additive (C,), alpha (K,C), basis (C,2n'), mean (2n',);
    output_scale (1.0, for the model directory's record).
    """

    per_vertex = True  # predicts d at the vertices, not an atlas image

    def __init__(self, config: GPConfig):
        super().__init__()
        config.validate()
        self.config = config
        k, p, c, n = config.num_train, config.pose_dim, config.components, config.num_vertices
        f64 = {"dtype": torch.float64}
        self.register_buffer("pose_mean", torch.zeros(p, **f64))
        self.register_buffer("pose_std", torch.ones(p, **f64))
        self.register_buffer("inputs", torch.zeros(k, p, **f64))
        self.register_buffer("log_lengthscale", torch.zeros(c, p, **f64))
        self.register_buffer("log_signal", torch.zeros(c, **f64))
        self.register_buffer("log_additive", torch.zeros(c, **f64))
        self.register_buffer("alpha", torch.zeros(k, c, **f64))
        self.register_buffer("basis", torch.zeros(c, 2 * n, **f64))
        self.register_buffer("mean", torch.zeros(2 * n, **f64))
        self.register_buffer("output_scale", torch.tensor(1.0))

    def forward(self, poses: torch.Tensor) -> torch.Tensor:
        z = (poses.to(torch.float64) - self.pose_mean) / self.pose_std
        coef = torch.empty(len(z), self.config.components, dtype=torch.float64, device=z.device)
        for c in range(self.config.components):
            k = _kernel(z, self.inputs, self.log_lengthscale[c], self.log_signal[c], self.log_additive[c])
            coef[:, c] = k @ self.alpha[:, c]
        d = self.mean + coef @ self.basis
        return d.reshape(len(z), -1, 2).to(torch.float32)

    def relevance(self) -> np.ndarray:
        """(C,P) inverse lengthscales: how much each pose coordinate moves each mode."""
        return torch.exp(-self.log_lengthscale).cpu().numpy()


def _kernel(a: torch.Tensor, b: torch.Tensor, log_lengthscale: torch.Tensor, log_signal: torch.Tensor,
            log_additive: torch.Tensor) -> torch.Tensor:
    """Kernel matrix (len(a), len(b)): a squared-exponential ARD kernel plus an additive one
    (a sum over pose coordinates of one-dimensional squared exponentials, same lengthscales)."""
    scale = torch.exp(-log_lengthscale)
    a, b = a * scale, b * scale
    k = torch.exp(2 * log_signal - 0.5 * torch.cdist(a, b).square())
    additive = torch.zeros_like(k)
    for i in range(a.shape[1]):  # one (n, m) matrix at a time, not an (n, m, P) array
        additive = additive + torch.exp(-0.5 * (a[:, i, None] - b[None, :, i]).square())
    return k + torch.exp(2 * log_additive) * additive


def loo_residuals(inverse: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Leave-one-out residuals y_i - E[y_i | y_-i] of a GP in closed form (Rasmussen &
    Williams, eq. 5.12): [A⁻¹y]_i / [A⁻¹]_ii, with A = K + σ²I and `inverse` = A⁻¹ (K,K)."""
    return (inverse @ y) / torch.diagonal(inverse)


def _fit_component(z: torch.Tensor, y: torch.Tensor, iterations: int,
                   hyper: np.ndarray | None = None) -> tuple[torch.Tensor, ...]:
    """One GP: hyperparameters by maximum marginal likelihood, then its posterior weights.

    The likelihood has poor local optima (a lengthscale collapsing onto one pose coordinate
    to explain noise), so L-BFGS starts from `_STARTS` and the lowest negative log
    likelihood wins; lengthscales are bounded below by exp(`_LOG_L_MIN`). The
    hyperparameters are fitted on the rows `hyper` (all when None), the posterior uses
    every row. A component whose leave-one-out error is no better than predicting 0 gets
    α = 0.

    Args:
        z: (K,P) standardised poses. y: (K,) targets, unit variance.

    Returns:
        log_lengthscale (P,), log_signal (), log_additive (), alpha (K,) (in y's units).
    """
    p = z.shape[1]
    floor = 1e-6  # noise variance floor (y has unit variance): keeps the covariance well conditioned
    zh, yh = (z, y) if hyper is None else (z[hyper], y[hyper])

    def covariance(points, log_l, log_s, log_n, log_a):
        return (_kernel(points, points, log_l.clamp(_LOG_L_MIN, 6.0), log_s.clamp(-6.0, 3.0), log_a.clamp(-8.0, 3.0))
                + (torch.exp(2 * log_n) + floor) * torch.eye(len(points), dtype=torch.float64))

    def objective(params):
        chol, info = torch.linalg.cholesky_ex(covariance(zh, *params))
        if int(info):
            return None
        a = torch.cholesky_solve(yh[:, None], chol)[:, 0]
        return 0.5 * (yh @ a) + torch.log(torch.diagonal(chol)).sum()

    best = fallback = None
    starts = [[torch.full((p,), math.log(lengthscale), dtype=torch.float64), torch.zeros((), dtype=torch.float64),
               torch.tensor(math.log(noise), dtype=torch.float64), torch.tensor(additive, dtype=torch.float64)]
              for lengthscale, noise, additive in _STARTS]
    while starts:
        params = [q.clone().requires_grad_(True) for q in starts.pop(0)]
        optimiser = torch.optim.LBFGS(params, lr=0.5, max_iter=iterations, history_size=20,
                                      line_search_fn="strong_wolfe", tolerance_grad=1e-7, tolerance_change=1e-10)

        def closure():
            optimiser.zero_grad()
            nll = objective(params)
            if nll is None:  # not positive definite here: a large value the line search backs off from
                nll = sum(q.sum() for q in params) * 0.0 + 1e30
            nll.backward()
            return nll

        optimiser.step(closure)
        with torch.no_grad():
            nll = objective(params)
        if nll is not None and torch.isfinite(nll) and (best is None or float(nll) < best[0]):
            best = (float(nll), [q.detach() for q in params])
        if not starts and hyper is not None and best is not None:
            # Refine the subset's best on more poses (all, up to a memory budget): a few
            # iterations from a good start.
            refine = evenly_spaced(len(z), max(len(hyper), int(math.sqrt(_REFINE_ELEMENTS / p))))
            zh, yh, hyper, iterations = z[refine], y[refine], None, _REFINE_ITERATIONS
            starts, fallback, best = [best[1]], best[1], None
    if best is None and fallback is None:
        raise ValueError("no Gaussian-process fit: the covariance is singular at every start")
    log_l, log_s, log_n, log_a = best[1] if best is not None else fallback
    chol, info = torch.linalg.cholesky_ex(covariance(z, log_l, log_s, log_n, log_a))
    if int(info):
        raise ValueError("no Gaussian-process fit: the covariance of all training poses is singular")
    inverse = torch.cholesky_inverse(chol)
    alpha = inverse @ y
    # A component the GP predicts no better than its mean (0) from the other poses is left at 0.
    if not float(loo_residuals(inverse, y).square().mean()) < float(y.square().mean()):
        alpha = torch.zeros_like(alpha)
    return log_l.clamp(_LOG_L_MIN, 6.0), log_s.clamp(-6.0, 3.0), log_a.clamp(-8.0, 3.0), alpha


def evenly_spaced(k: int, count: int) -> np.ndarray:
    """`count` evenly spaced indices of range(k) (all of them when count >= k)."""
    return np.arange(k) if count >= k else np.unique(np.linspace(0, k - 1, count).round().astype(int))


def fit_pose_gp(poses: np.ndarray, d: np.ndarray, components: int = 32, iterations: int = 60,
                progress: Callable[[int, int], None] | None = None) -> PoseGP:
    """Fit a `PoseGP` to training displacements.

    Args:
        poses: (K,P) training pose vectors; K at most `MAX_TRAIN` (the caller subsamples).
        d: (K,n',2) their displacements.
        components: principal components modelled (fewer when K - 1 is smaller).
        iterations: L-BFGS iterations per component.
        progress: called with (components done, components) after each one.
    """
    x = np.asarray(poses, dtype=np.float64)
    y = np.asarray(d, dtype=np.float64).reshape(len(d), -1)
    k, p = x.shape
    if len(y) != k or k < 1:
        raise ValueError(f"expected poses (K,P) and d (K,n',2) with K >= 1, got {x.shape} and {np.shape(d)}")
    mean_x, std_x = x.mean(0), x.std(0)
    std_x = np.where(std_x > 1e-12, std_x, 1.0)
    mean_d = y.mean(0)
    centred = y - mean_d
    # PCA through the (K,K) Gram matrix: K is small, 2n' is not.
    eigval, eigvec = np.linalg.eigh(centred @ centred.T)
    order = np.argsort(eigval)[::-1][: max(0, min(components, k - 1))]
    order = order[eigval[order] > 1e-12 * max(float(eigval.max(initial=0.0)), 1e-300)]
    basis = (eigvec[:, order].T @ centred) / np.sqrt(eigval[order])[:, None]  # (C,2n') orthonormal rows
    coef = centred @ basis.T  # (K,C)
    config = GPConfig(pose_dim=p, num_vertices=y.shape[1] // 2, num_train=k, components=len(order))
    model = PoseGP(config)
    z = torch.from_numpy((x - mean_x) / std_x)
    # Hyperparameters from at most HYPER_POSES evenly spaced poses (O(K^3) per likelihood
    # evaluation); the posterior conditions on all of them.
    hyper = None if k <= HYPER_POSES else evenly_spaced(k, HYPER_POSES)
    with torch.no_grad():
        model.pose_mean.copy_(torch.from_numpy(mean_x))
        model.pose_std.copy_(torch.from_numpy(std_x))
        model.inputs.copy_(z)
        model.basis.copy_(torch.from_numpy(basis))
        model.mean.copy_(torch.from_numpy(mean_d))
    for c in range(len(order)):
        scale = float(coef[:, c].std()) or 1.0
        log_l, log_s, log_a, alpha = _fit_component(z, torch.from_numpy(coef[:, c] / scale), iterations, hyper)
        with torch.no_grad():
            model.log_lengthscale[c] = log_l
            model.log_signal[c] = log_s + math.log(scale)  # kernel in coefficient units...
            model.log_additive[c] = log_a + math.log(scale)
            model.alpha[:, c] = alpha / scale  # ...and α / scale: k α = scale² k̃ α̃ / scale = scale k̃ α̃
        if progress is not None:
            progress(c + 1, len(order))
    model.eval()
    return model
