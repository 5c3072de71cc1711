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
s_c, t_c and noise, chosen by maximising the log marginal likelihood; prediction is the
posterior mean k_c(θ, Θ) α_c with α_c = (K_c + σ_c² I)⁻¹ y_c, and a component whose
leave-one-out error is no better than predicting 0 gets α_c = 0. Nothing is learned per
texel, so it needs no atlas: it reads and writes d at the vertices. The exact GP costs
O(K³) in the number of training poses, so at most `MAX_TRAIN` (evenly spaced) training
poses are used; beyond that the networks have the data they need.

The fit. The C likelihoods are independent, so they are evaluated together: a batched
Cholesky factorisation of the (C,K,K) covariances and the closed-form gradient
½ tr((A⁻¹ - ααᵀ) ∂A/∂θ), summed tile by tile over the upper triangle of pose pairs, so no
autograd graph is kept and the (C,K,K,P) array of one-dimensional terms never exists
whole. Each component keeps its own L-BFGS (`mvtex.tsnn.lbfgs`: its own history, line
search and stopping test, bounds kept by projection), so a component follows the path it
would follow alone, and finished components cost nothing more. The bounds (the lengthscale
floor among them) are kept by projection, so a lengthscale that reached its cap can come
back; a clamp's flat region past the cap would hold it there for good. The fit runs on
`HYPER_POSES` evenly spaced training poses (on all of them up to that count; the posterior
conditions on all): from three starts, the best kept per
component, up to `MULTI_START_POSES` poses, from one (ℓ = 1, σ = 0.1, t = e⁻²) above,
where it predicts the test poses as well as three starts do
(benchmarks/tsnn_learning_curve.py, `gp` beside `gp_reference`). On the CPU the batch is cut into parts
evaluated side by side on as many Python threads as torch has threads, each operation
on one thread: one join per evaluation instead of a barrier per operation (on a shared
machine, per-operation barriers make two threads several times slower than one). The
parts do not depend on the thread count, so the fit is deterministic and the same bits
on one thread or several. The same code takes CUDA tensors (float64, larger tiles).

GPyTorch's batched exact GPs (ScaleKernel(RBFKernel(ARD)) + ScaleKernel(AdditiveStructure
Kernel(the same RBFKernel))) compute the same likelihood (benchmarks/gp_fit.py checks it)
but by autograd through (C,P,K,K) kernel tensors: 5-10 times slower per evaluation here,
with memory growing as C·P·K², and a dependency; so the fit is written here.

It is an `nn.Module` with buffers only, so a model directory stores it like the networks
(model.safetensors + config.json "architecture": {"arch": "gp", ...}).
"""

from __future__ import annotations

import contextlib
import math
import threading
from dataclasses import asdict, dataclass, fields
from typing import Any, Callable

import numpy as np
import torch
from torch import nn

MAX_TRAIN = 2000  # training poses an exact GP is fitted on (O(K^3) time, O(K^2) memory)


# Above MAX_TRAIN training poses the posterior mean is that of the subset-of-regressors
# approximation on INDUCING_POSES evenly spaced training poses (O(K M^2) time, O(K M) memory
# per component): every training pose informs the prediction, and the model keeps the same
# form (a kernel expansion on M poses).
INDUCING_POSES = MAX_TRAIN


# Training poses of at most this many are read at once when the principal components of d
# are projected (float64 rows of 2n' values).
_PCA_CHUNK = 256


MAX_COMPONENTS = 256


# Training poses the hyperparameters are fitted on (evenly spaced); the posterior uses all.
# On the built-in T-shirt (camera left), 400 of 960 training poses fit 14 times faster but
# leave the test poses' same-chart ratio 7 % below the component-by-component reference's
# (benchmarks/tsnn_learning_curve.py); all of them hold it.
HYPER_POSES = 1000


# (lengthscale, noise std, log std of the additive part) at the start, standardised units
_START = (1.0, 0.1, -2.0)


# Up to this many training poses the likelihood is cheap, and the fit runs from every start
# of _STARTS (the best kept per component): on the built-in T-shirt (camera left) that lowers
# the test poses' displacement error by 1.5 % at 120 poses and 1 % at 240, for 2.5 times the
# fit time; above it, one start (_START).
MULTI_START_POSES = 300


_STARTS = (_START, (4.0, 0.1, -2.0), (1.0, 0.5, 0.0))


# Shortest lengthscale, in training standard deviations of the pose coordinate: shorter ones
# only fit noise (a few hundred poses cannot resolve them in a dozen dimensions).
_LOG_L_MIN = math.log(0.3)


_NOISE_FLOOR = 1e-6  # noise variance floor (y has unit variance): keeps the covariance well conditioned


_PART_ROWS = 8  # rows of one part of a batched likelihood evaluation (see `_parts`)


_PART_ELEMENTS = 2 ** 23  # (rows, K, K) float64 arrays of one part: 64 MB each


_DEVICE_SCALE = 16  # larger tiles and parts on CUDA: fewer, larger kernels


_TILE_ELEMENTS = 2 ** 18  # (rows, tile, tile, P) temporaries of the kernel: 2 MB of float64, cache-sized


def integer_config(cls, d: dict[str, Any], arch: str):
    """A config dataclass of integer fields from its dict (config.json's "architecture",
    "arch" left out), validated: ValueError on unknown keys or values that are not integers."""
    d = {k: v for k, v in d.items() if k != "arch"}
    unknown = set(d) - {f.name for f in fields(cls)}
    if unknown:
        raise ValueError(f"unknown architecture keys {sorted(unknown)}")
    if any(isinstance(v, bool) or not isinstance(v, int) for v in d.values()):
        raise ValueError(f"{arch} architecture values must be integers")
    config = cls(**d)
    config.validate()
    return config


@dataclass(frozen=True)
class GPConfig:
    """Shape of a `PoseGP`.

    Attributes:
        pose_dim: P, length of the pose vector.
        num_vertices: n', vertices the displacements are predicted at.
        num_train: K, poses the posterior mean is expanded on: the training poses (at most
            `MAX_TRAIN`), or the inducing poses of a fit on more training poses.
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
        return integer_config(cls, d, "gp")


class PoseGP(nn.Module):
    """Posterior mean of per-component GPs: pose (B,P) -> d (B,n',2), float32; and its
    predictive standard deviation per vertex (`predictive_std`).

    Buffers (float64): pose_mean/pose_std (P,), inputs (K,P) standardised training poses,
    log_lengthscale (C,P), log_signal (C,), log_additive (C,), alpha (K,C), basis (C,2n'), mean (2n',);
    output_scale (1.0, for the model directory's record); for the predictive variance,
    log_noise (C,) the log noise std of each component and residual_var (2n',) the mean
    square of what the C components leave of the training displacements (the PCA
    truncation), both NaN in a model stored without them (it reports no uncertainty).
    """

    per_vertex = True  # predicts d at the vertices, not an atlas image

    # Buffers a stored model may lack (one written before they existed): NaN then.
    optional_buffers = ("log_noise", "residual_var")

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
        self.register_buffer("log_noise", torch.full((c,), math.nan, **f64))
        self.register_buffer("residual_var", torch.full((2 * n,), math.nan, **f64))
        self._factors: tuple | None = None  # Cholesky factors of the training covariances, made on first use

    @property
    def has_uncertainty(self) -> bool:
        """True when the model holds what `predictive_std` needs."""
        return bool(torch.isfinite(self.log_noise).all() and torch.isfinite(self.residual_var).all())

    def _cholesky(self) -> list[torch.Tensor]:
        """Per component, the Cholesky factor of K_c(Θ,Θ) + σ_c² I (coefficient units)."""
        key = tuple(float(t.sum()) for t in (self.inputs, self.log_lengthscale, self.log_signal,
                                              self.log_additive, self.log_noise))
        if self._factors is None or self._factors[0] != key:
            factors = []
            for c in range(self.config.components):
                a = _kernel(self.inputs, self.inputs, self.log_lengthscale[c], self.log_signal[c], self.log_additive[c])
                a.diagonal().add_(torch.exp(2 * self.log_noise[c]))
                factors.append(torch.linalg.cholesky(a))
            self._factors = (key, factors)
        return self._factors[1]

    def predictive_std(self, poses: torch.Tensor) -> torch.Tensor | None:
        """Predictive standard deviation of d per vertex, (B,n') float64 in uv units: the
        root of the expected squared length of d's error, sqrt(var_u + var_v).

        Per component c, the GP's predictive variance of a new pose's coefficient,
        k_c(θ,θ) - k_c(θ,Θ) (K_c + σ_c² I)⁻¹ k_c(Θ,θ) + σ_c² (the coefficients of the
        training displacements are noisy observations, and so are a new pose's); a component
        predicted as 0 (α_c = 0) has its prior variance k_c(θ,θ) + σ_c². The components are
        independent, so var(d_j) = Σ_c var_c basis_cj², plus residual_var_j, what the
        truncated components left of the training displacements. None when the model
        holds no noise levels (`has_uncertainty`).
        """
        if not self.has_uncertainty:
            return None
        z = (poses.to(torch.float64) - self.pose_mean) / self.pose_std
        c_count, p = self.config.components, self.config.pose_dim
        noise = torch.exp(2 * self.log_noise)
        prior = torch.exp(2 * self.log_signal) + p * torch.exp(2 * self.log_additive)  # k_c(θ,θ) (C,)
        var = (prior + noise)[None, :].expand(len(z), -1).clone()  # (B,C)
        if c_count:
            k = kernel_matrix(z, self.inputs, self.log_lengthscale, self.log_signal, self.log_additive)  # (C,B,K)
            predicted = (self.alpha != 0).any(0)
            for c, chol in enumerate(self._cholesky()):
                if bool(predicted[c]):
                    v = torch.linalg.solve_triangular(chol, k[c].T, upper=False)  # (K,B)
                    var[:, c] -= v.square().sum(0)
            var = var.clamp_min(0.0)
        per_coordinate = var @ self.basis.square() + self.residual_var  # (B,2n')
        return per_coordinate.reshape(len(z), -1, 2).sum(-1).sqrt()

    def forward(self, poses: torch.Tensor) -> torch.Tensor:
        z = (poses.to(torch.float64) - self.pose_mean) / self.pose_std
        k = kernel_matrix(z, self.inputs, self.log_lengthscale, self.log_signal, self.log_additive)  # (C,B,K)
        coef = torch.einsum("cbk,kc->bc", k, self.alpha)
        d = self.mean + coef @ self.basis
        return d.reshape(len(z), -1, 2).to(torch.float32)

    def relevance(self) -> np.ndarray:
        """(C,P) inverse lengthscales: how much each pose coordinate moves each mode."""
        return torch.exp(-self.log_lengthscale).cpu().numpy()


def _tiles(n: int, size: int) -> list[tuple[int, int]]:
    return [(i, min(i + size, n)) for i in range(0, n, size)]


def _tile_size(rows: int, p: int, device) -> int:
    budget = _TILE_ELEMENTS * (1 if torch.device(device).type == "cpu" else _DEVICE_SCALE)
    return max(8, int(math.sqrt(budget / max(1, rows * p))))


def _tile_terms(a: torch.Tensor, b: torch.Tensor, half: torch.Tensor):
    """The squared differences of one tile and its two kernel terms, without their variances.

    Args:
        a: (n,P), b: (m,P) standardised poses. half: (R,P) -1/(2ℓ²) of R kernels.

    Returns:
        d2 (n,m,P) (θ_i - θ'_i)², ard exp(-½ Σ_i r_i²) (R,n,m), additive Σ_i exp(-½ r_i²)
        (R,n,m) and e (R,n,m,P) the terms exp(-½ r_i²).
    """
    d2 = (a[:, None, :] - b[None, :, :]).square()
    e = torch.exp(d2[None] * half[:, None, None, :])
    ard = torch.exp(torch.einsum("klp,rp->rkl", d2, half))
    return d2, ard, e.sum(-1), e


def kernel_matrix(a: torch.Tensor, b: torch.Tensor, log_lengthscale: torch.Tensor, log_signal: torch.Tensor,
                  log_additive: torch.Tensor) -> torch.Tensor:
    """Kernel matrices of R kernels, (R, len(a), len(b)) float64: a squared-exponential ARD
    kernel plus an additive one (a sum over pose coordinates of one-dimensional squared
    exponentials, same lengthscales), computed tile by tile (no (R,n,m,P) array whole).

    Args:
        a: (n,P), b: (m,P) standardised poses. log_lengthscale: (R,P). log_signal, log_additive: (R,).
    """
    rows, p = log_lengthscale.shape
    size = _tile_size(rows, p, a.device)
    half = -0.5 * torch.exp(-2 * log_lengthscale)
    s2, t2 = torch.exp(2 * log_signal)[:, None, None], torch.exp(2 * log_additive)[:, None, None]
    out = torch.empty(rows, len(a), len(b), dtype=a.dtype, device=a.device)
    for i0, i1 in _tiles(len(a), size):
        for j0, j1 in _tiles(len(b), size):
            _, ard, additive, _ = _tile_terms(a[i0:i1], b[j0:j1], half)
            out[:, i0:i1, j0:j1] = s2 * ard + t2 * additive
    return out


def _kernel(a: torch.Tensor, b: torch.Tensor, log_lengthscale: torch.Tensor, log_signal: torch.Tensor,
            log_additive: torch.Tensor) -> torch.Tensor:
    """The kernel matrix (len(a), len(b)) of one set of hyperparameters (see `kernel_matrix`)."""
    return kernel_matrix(a, b, log_lengthscale[None], log_signal.reshape(1), log_additive.reshape(1))[0]


def loo_residuals(inverse: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Leave-one-out residuals y_i - E[y_i | y_-i] of a GP in closed form (Rasmussen &
    Williams, eq. 5.12): [A⁻¹y]_i / [A⁻¹]_ii, with A = K + σ²I and `inverse` = A⁻¹ (...,K,K)
    (batched over leading dimensions; y (...,K))."""
    return (inverse @ y[..., None])[..., 0] / torch.diagonal(inverse, dim1=-2, dim2=-1)


def _bounds(p: int, device) -> tuple[torch.Tensor, torch.Tensor]:
    """Lower and upper bounds of a parameter row [log ℓ (P), log s, log σ, log t]."""
    inf = math.inf
    lo = torch.tensor([_LOG_L_MIN] * p + [-6.0, -inf, -8.0], dtype=torch.float64, device=device)
    hi = torch.tensor([6.0] * p + [3.0, inf, 3.0], dtype=torch.float64, device=device)
    return lo, hi


def _covariance(z: torch.Tensor, params: torch.Tensor) -> torch.Tensor:
    """A = K + (σ² + floor) I of R parameter rows (R, P+3) (already within bounds): (R,K,K).
    Only the tiles on and above the diagonal are computed; the others are their transposes."""
    rows, p = len(params), z.shape[1]
    size = _tile_size(rows, p, z.device)
    half = -0.5 * torch.exp(-2 * params[:, :p])
    s2, t2 = torch.exp(2 * params[:, p])[:, None, None], torch.exp(2 * params[:, p + 2])[:, None, None]
    a = torch.empty(rows, len(z), len(z), dtype=z.dtype, device=z.device)
    tiles = _tiles(len(z), size)
    for n, (i0, i1) in enumerate(tiles):
        for j0, j1 in tiles[n:]:
            _, ard, additive, _ = _tile_terms(z[i0:i1], z[j0:j1], half)
            a[:, i0:i1, j0:j1] = s2 * ard + t2 * additive
            if j0 != i0:
                a[:, j0:j1, i0:i1] = a[:, i0:i1, j0:j1].transpose(1, 2)
    a.diagonal(dim1=1, dim2=2).add_((torch.exp(2 * params[:, p + 1]) + _NOISE_FLOOR)[:, None])
    return a


def _negative_log_likelihood(z: torch.Tensor, y: torch.Tensor, params: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Negative log marginal likelihoods ½ yᵀA⁻¹y + ½ log|A| of R GPs and their gradients.

    The gradient is the closed form ∂/∂θ = ½ tr((A⁻¹ - ααᵀ) ∂A/∂θ), α = A⁻¹y (Rasmussen &
    Williams, eq. 5.9), summed tile by tile with the kernel terms computed again (cheaper
    than keeping them): no autograd graph and no (R,K,K,P) array. Parameters outside their
    bounds act at the bound, with no gradient (as a clamp would).

    Args:
        z: (K,P) standardised poses. y: (R,K) targets. params: (R,P+3) rows
            [log ℓ (P), log s, log σ, log t].

    Returns:
        nll (R,) (inf where A is not positive definite) and its gradient (R,P+3).
    """
    rows, p = len(params), z.shape[1]
    lo, hi = _bounds(p, z.device)
    inside = (params >= lo) & (params <= hi)
    q = torch.maximum(torch.minimum(params, hi), lo)
    a = _covariance(z, q)
    chol, info = torch.linalg.cholesky_ex(a)
    del a
    bad = info != 0
    if bool(bad.any()):  # factor the identity there, so the rest of the batch goes on
        chol = torch.where(bad[:, None, None], torch.eye(len(z), dtype=z.dtype, device=z.device), chol)
    alpha = torch.cholesky_solve(y[:, :, None], chol)[:, :, 0]
    nll = 0.5 * (y * alpha).sum(1) + torch.log(torch.diagonal(chol, dim1=1, dim2=2)).sum(1)
    inverse = torch.cholesky_inverse(chol)
    del chol
    inverse_square = torch.exp(-2 * q[:, :p])
    half = -0.5 * inverse_square
    s2, t2 = torch.exp(2 * q[:, p]), torch.exp(2 * q[:, p + 2])
    g_ard = torch.zeros(rows, dtype=z.dtype, device=z.device)
    g_additive = torch.zeros_like(g_ard)
    g_length = torch.zeros(rows, p, dtype=z.dtype, device=z.device)
    tiles = _tiles(len(z), _tile_size(rows, p, z.device))
    for n, (i0, i1) in enumerate(tiles):
        for j0, j1 in tiles[n:]:
            twice = 1.0 if j0 == i0 else 2.0  # an off-diagonal tile stands for its transpose too
            w = inverse[:, i0:i1, j0:j1] - alpha[:, i0:i1, None] * alpha[:, None, j0:j1]
            d2, ard, additive, e = _tile_terms(z[i0:i1], z[j0:j1], half)
            w_ard = w * ard
            g_ard += twice * w_ard.sum((1, 2))
            g_additive += twice * (w * additive).sum((1, 2))
            # ∂A/∂log ℓ_i = (s² ard + t² e_i) d2_i / ℓ_i²
            g_length += (0.5 * twice) * (s2[:, None] * torch.einsum("rkl,klp->rp", w_ard, d2)
                                         + t2[:, None] * torch.einsum("rkl,rklp->rp", w, e.mul_(d2)))
    g_length *= inverse_square
    trace = torch.diagonal(inverse, dim1=1, dim2=2).sum(1) - (alpha * alpha).sum(1)
    grad = torch.cat([g_length, (s2 * g_ard)[:, None], (torch.exp(2 * q[:, p + 1]) * trace)[:, None],
                      (t2 * g_additive)[:, None]], 1) * inside
    nll = torch.where(bad, torch.full_like(nll, math.inf), nll)
    return nll, torch.where(bad[:, None], torch.zeros_like(grad), grad)


def _parts(rows: int, k: int, device) -> list[slice]:
    """Consecutive parts of a batch of rows on K poses: on the CPU at most `_PART_ROWS` rows,
    and a few (rows,K,K) arrays within `_PART_ELEMENTS` (on CUDA, `_DEVICE_SCALE` times
    that, and rows without a limit). The split depends on the batch alone, never on the
    number of threads, so neither do a row's bits."""
    if torch.device(device).type == "cpu":
        size = max(1, min(_PART_ROWS, _PART_ELEMENTS // (k * k)))
    else:
        size = max(1, _PART_ELEMENTS * _DEVICE_SCALE // (k * k))
    return [slice(i, min(i + size, rows)) for i in range(0, rows, size)]


def _map(pool, fn, parts):
    return list(pool.map(fn, parts)) if pool is not None else [fn(part) for part in parts]


@contextlib.contextmanager
def _workers(device):
    """Threads that evaluate the parts of a batch side by side, each on one torch thread
    (None on CUDA: one device). Inside, torch runs one thread per operation: the parts are
    the parallel work, one join per batch instead of a barrier per operation (on a shared
    machine those barriers make two intra-op threads several times slower than one)."""
    if torch.device(device).type != "cpu":
        yield None
        return
    from concurrent.futures import ThreadPoolExecutor

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        pool = ThreadPoolExecutor(threads, thread_name_prefix="mvtex-gp") if threads > 1 else None
        with pool or contextlib.nullcontext():
            yield pool
    finally:
        torch.set_num_threads(threads)


def _objective(z: torch.Tensor, y: torch.Tensor, pool=None):
    """The `lbfgs.minimise` objective of parameter rows on poses z (K,P), targets y (R,K)."""

    def objective(x: torch.Tensor, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        parts = _map(pool, lambda part: _negative_log_likelihood(z, y[rows[part]], x[part]),
                     _parts(len(x), len(z), z.device))
        return torch.cat([f for f, _ in parts]), torch.cat([g for _, g in parts])

    return objective


def _start(c: int, p: int, device, start: tuple[float, float, float] = _START) -> torch.Tensor:
    """(C, P+3) starting rows: (lengthscale, noise std, log std of the additive part)."""
    length, noise, additive = start
    row = torch.tensor([math.log(length)] * p + [0.0, math.log(noise), additive], dtype=torch.float64, device=device)
    return row.expand(c, -1).clone()


def _fit_hyperparameters(z: torch.Tensor, y: torch.Tensor, iterations: int, pool=None,
                         starts: tuple[tuple[float, float, float], ...] = (_START,),
                         progress: Callable[[int, int], None] | None = None) -> torch.Tensor:
    """Hyperparameter rows (C,P+3) [log ℓ, log s, log σ, log t] of C GPs on poses z (K,P)
    with unit-variance targets y (C,K), by maximum marginal likelihood, all at once (on the
    threads of `pool`, or of its own `_workers`); from each of `starts`, the best kept."""
    from mvtex.tsnn.lbfgs import minimise

    lo, hi = _bounds(z.shape[1], z.device)
    c, p = len(y), z.shape[1]
    x0 = torch.cat([_start(c, p, z.device, start) for start in starts])
    with _workers(z.device) if pool is None else contextlib.nullcontext(pool) as threads:
        result = minimise(_objective(z, y.repeat(len(starts), 1), threads), x0, iterations, lo, hi,
                          progress=progress)
    f = torch.where(torch.isfinite(result.f), result.f, torch.inf).reshape(len(starts), c)
    if not bool(torch.isfinite(f).any(0).all()):
        raise ValueError("no Gaussian-process fit: the covariance is singular at the start")
    best = f.argmin(0)
    return result.x.reshape(len(starts), c, -1)[best, torch.arange(c, device=best.device)]


def _posterior(z: torch.Tensor, y: torch.Tensor, params: torch.Tensor, pool=None,
               done: Callable[[int], None] | None = None) -> torch.Tensor:
    """α = A⁻¹y (C,K) of C GPs on every pose; 0 for a component whose leave-one-out error
    is no better than predicting 0. `done(rows)` is called as each part of the rows is done."""
    lo, hi = _bounds(z.shape[1], z.device)
    q = torch.maximum(torch.minimum(params, hi), lo)

    def part_alpha(part: slice) -> torch.Tensor:
        chol, info = torch.linalg.cholesky_ex(_covariance(z, q[part]))
        if bool((info != 0).any()):
            raise ValueError("no Gaussian-process fit: the covariance of all training poses is singular")
        inverse = torch.cholesky_inverse(chol)
        a = (inverse @ y[part, :, None])[:, :, 0]
        useless = ~(loo_residuals(inverse, y[part]).square().mean(1) < y[part].square().mean(1))
        if done is not None:
            done(part.stop - part.start)
        return torch.where(useless[:, None], torch.zeros_like(a), a)

    with _workers(z.device) if pool is None else contextlib.nullcontext(pool) as threads:
        return torch.cat(_map(threads, part_alpha, _parts(len(y), len(z), z.device)))


def evenly_spaced(k: int, count: int) -> np.ndarray:
    """`count` evenly spaced indices of range(k) (all of them when count >= k)."""
    return np.arange(k) if count >= k else np.unique(np.linspace(0, k - 1, count).round().astype(int))


def pose_pca(poses: np.ndarray, d, components: int, basis_poses: int = MAX_TRAIN,
             progress: Callable[[int, int], None] | None = None):
    """The principal components of d that a `PoseGP` models, and the pose standardisation.

    Args:
        poses: (K,P) pose vectors.
        d: (K,n',2) displacements: an array, or anything that `d[rows]` (rows: an int64
            index array) reads rows of, so a large training set is never held whole.
        components: most principal components.
        basis_poses: the components are those of at most this many evenly spaced poses;
            every pose's coefficients are projections on them (read `_PCA_CHUNK` at a time).
        progress: called with (chunks read, chunks) as the poses are read.

    Returns (x (K,P), mean_x, std_x, mean_d (2n',), basis (C,2n') with orthonormal rows,
    coef (K,C)); C is at most `components` and K' - 1 (K' = min(K, basis_poses)), without
    null directions.
    """
    x = np.asarray(poses, dtype=np.float64)
    k = len(x)
    if x.ndim != 2 or len(d) != k or k < 1 or len(np.shape(d)) != 3:
        raise ValueError(f"expected poses (K,P) and d (K,n',2) with K >= 1, got {x.shape} and {np.shape(d)}")
    mean_x, std_x = x.mean(0), x.std(0)
    std_x = np.where(std_x > 1e-12, std_x, 1.0)
    rows = evenly_spaced(k, basis_poses)
    chunks = [rows[i:i + _PCA_CHUNK] for i in range(0, len(rows), _PCA_CHUNK)]
    total = len(chunks) + (0 if len(rows) == k else -(-k // _PCA_CHUNK))
    y = np.empty((len(rows), int(np.prod(np.shape(d)[1:]))))
    for i, chunk in enumerate(chunks):
        y[i * _PCA_CHUNK:i * _PCA_CHUNK + len(chunk)] = np.asarray(d[chunk], dtype=np.float64).reshape(len(chunk), -1)
        if progress is not None:
            progress(i + 1, total)
    mean_d = y.mean(0)
    centred = y - mean_d
    del y
    # PCA through the (K',K') Gram matrix: K' is small, 2n' is not.
    eigval, eigvec = np.linalg.eigh(centred @ centred.T)
    order = np.argsort(eigval)[::-1][: max(0, min(components, len(rows) - 1))]
    order = order[eigval[order] > 1e-12 * max(float(eigval.max(initial=0.0)), 1e-300)]
    basis = (eigvec[:, order].T @ centred) / np.sqrt(eigval[order])[:, None]
    if len(rows) == k:
        coef = centred @ basis.T
    else:
        del centred
        coef = np.empty((k, len(basis)))
        for i0 in range(0, k, _PCA_CHUNK):
            chunk = np.arange(i0, min(i0 + _PCA_CHUNK, k))
            coef[chunk] = (np.asarray(d[chunk], dtype=np.float64).reshape(len(chunk), -1) - mean_d) @ basis.T
            if progress is not None:
                progress(len(chunks) + i0 // _PCA_CHUNK + 1, total)
    return x, mean_x, std_x, mean_d, basis, coef


def pose_pca_counted(poses: np.ndarray, d, components: int,
                     progress: Callable[[int, int], None] | None = None):
    """`pose_pca` with its default basis, and how many progress steps its reading took (the
    first steps of a fit's progress, which then goes on counting from there)."""
    reads = [0]

    def reading(done: int, total: int) -> None:
        reads[0] = total
        if progress is not None:
            progress(done, total)

    return pose_pca(poses, d, components, progress=reading), reads[0]


def _residual_var(d, mean_d: np.ndarray, basis: np.ndarray, coef: np.ndarray) -> np.ndarray:
    """Per coordinate (2n',), the mean square over the training poses of what the principal
    components leave of d (the PCA truncation residual), read `_PCA_CHUNK` poses at a time."""
    k = len(coef)
    total = np.zeros(len(mean_d))
    for i0 in range(0, k, _PCA_CHUNK):
        chunk = np.arange(i0, min(i0 + _PCA_CHUNK, k))
        rows = np.asarray(d[chunk], dtype=np.float64).reshape(len(chunk), -1) - mean_d
        total += ((rows - coef[chunk] @ basis) ** 2).sum(0)
    return total / max(k, 1)


def _inducing_alpha(z: torch.Tensor, y: torch.Tensor, params: torch.Tensor, inducing: torch.Tensor,
                    pool=None, done: Callable[[int], None] | None = None) -> torch.Tensor:
    """Subset-of-regressors posterior mean weights (C,M) of C GPs on all K poses z (K,P),
    expanded on the M poses z[inducing]: α = (σ² K_mm + K_mk K_km)⁻¹ K_mk y (Rasmussen &
    Williams, eq. 8.14), computed stably as L⁻ᵀ (σ²I + AAᵀ)⁻¹ A y with K_mm = LLᵀ and
    A = L⁻¹ K_mk. The prediction k(θ, Z_m) α is then the exact GP's when M = K.
    `done(rows)` is called as each part of the rows is done."""
    lo, hi = _bounds(z.shape[1], z.device)
    q = torch.maximum(torch.minimum(params, hi), lo)
    p = z.shape[1]
    zm = z[inducing]
    m = len(zm)

    def part_alpha(part: slice) -> torch.Tensor:
        rows = q[part]
        kmm = kernel_matrix(zm, zm, rows[:, :p], rows[:, p], rows[:, p + 2])
        eye = torch.eye(m, dtype=z.dtype, device=z.device)
        jitter = 1e-8 * kmm.diagonal(dim1=1, dim2=2).mean(1)
        for _ in range(6):
            chol, info = torch.linalg.cholesky_ex(kmm + jitter[:, None, None] * eye)
            if not bool((info != 0).any()):
                break
            jitter = jitter * 100
        else:
            raise ValueError("no Gaussian-process fit: the covariance of the inducing poses is singular")
        del kmm
        a = torch.linalg.solve_triangular(chol, kernel_matrix(zm, z, rows[:, :p], rows[:, p], rows[:, p + 2]),
                                          upper=False)  # (R,M,K)
        noise = torch.exp(2 * rows[:, p + 1]) + _NOISE_FLOOR
        b = a @ a.transpose(1, 2) + noise[:, None, None] * eye
        c = torch.cholesky_solve((a @ y[part, :, None]), torch.linalg.cholesky(b))
        if done is not None:
            done(part.stop - part.start)
        return torch.linalg.solve_triangular(chol.transpose(1, 2), c, upper=True)[:, :, 0]

    size = max(1, min(_PART_ROWS, _PART_ELEMENTS // (m * len(z))))
    parts = [slice(i, min(i + size, len(y))) for i in range(0, len(y), size)]
    with _workers(z.device) if pool is None else contextlib.nullcontext(pool) as threads:
        return torch.cat(_map(threads, part_alpha, parts))


def fit_pose_gp(poses: np.ndarray, d, components: int = 32, iterations: int = 40,
                progress: Callable[[int, int], None] | None = None, device: str | torch.device = "cpu",
                inducing: int = INDUCING_POSES) -> PoseGP:
    """Fit a `PoseGP` to training displacements.

    Args:
        poses: (K,P) training pose vectors.
        d: (K,n',2) their displacements, an array or anything `d[rows]` reads rows of
            (`pose_pca`).
        components: principal components modelled (fewer when K - 1 is smaller).
        iterations: most L-BFGS iterations per component. 40: on the built-in shirt (480
            training poses, camera left) the test poses' displacement error is within 0.01 %
            of that with 60 iterations, and the fit takes a third less time.
        progress: called with (steps done, steps) as the fit goes: the chunks of
            `_PCA_CHUNK` training poses read (`pose_pca`), the L-BFGS steps of every component (a stopped component counts as all its steps), then one step per
            component for the posterior (two above `inducing` training poses: the
            leave-one-out test on the hyperparameters' poses, then the inducing posterior).
        device: where the likelihoods are evaluated; the model comes back on the CPU.
        inducing: above this many training poses (at most `MAX_TRAIN`), the posterior mean
            is the subset-of-regressors one on this many evenly spaced training poses;
            up to it, the exact one on every training pose.
    """
    if not 1 <= inducing <= MAX_TRAIN:
        raise ValueError(f"inducing must be in 1..{MAX_TRAIN}, got {inducing}")
    (x, mean_x, std_x, mean_d, basis, coef), reads = pose_pca_counted(poses, d, components, progress)
    k, p = x.shape
    exact = k <= inducing
    expansion = np.arange(k) if exact else evenly_spaced(k, inducing)
    z = (x - mean_x) / std_x
    config = GPConfig(pose_dim=p, num_vertices=len(mean_d) // 2, num_train=len(expansion), components=len(basis))
    model = PoseGP(config)
    with torch.no_grad():
        model.pose_mean.copy_(torch.from_numpy(mean_x))
        model.pose_std.copy_(torch.from_numpy(std_x))
        model.inputs.copy_(torch.from_numpy(z[expansion]))
        model.basis.copy_(torch.from_numpy(basis))
        model.mean.copy_(torch.from_numpy(mean_d))
        model.residual_var.copy_(torch.from_numpy(_residual_var(d, mean_d, basis, coef)))
    if len(basis):
        scale = coef.std(0)
        scale = np.where(scale > 0, scale, 1.0)  # each GP fits unit-variance targets
        zt = torch.from_numpy(z).to(device)
        yt = torch.from_numpy((coef / scale).T.copy()).to(device)
        # Hyperparameters from at most HYPER_POSES evenly spaced poses (O(K^3) per likelihood
        # evaluation); the posterior conditions on all of them.
        hyper = torch.from_numpy(evenly_spaced(k, HYPER_POSES)).to(device)
        starts = _STARTS if len(hyper) <= MULTI_START_POSES else (_START,)
        steps = reads + len(basis) * len(starts) * iterations
        total = steps + len(basis) * (1 if exact else 2)
        finished = [0]
        lock = threading.Lock()

        def report(done: int, _: int) -> None:
            if progress is not None:
                progress(done, total)

        def rows_done(rows: int) -> None:  # from the worker threads
            with lock:
                finished[0] += rows
                report(steps + finished[0], total)

        with torch.no_grad(), _workers(device) as pool:
            params = _fit_hyperparameters(zt[hyper], yt[:, hyper], iterations, pool, starts,
                                          lambda done, _: report(reads + done, total))
            if exact:
                alpha = _posterior(zt, yt, params, pool, rows_done).cpu()
            else:
                # A component is kept if its leave-one-out error on the hyperparameters' poses
                # beats predicting 0 (the exact test, as below MAX_TRAIN).
                useful = _posterior(zt[hyper], yt[:, hyper], params, pool, rows_done).abs().sum(1) > 0
                alpha = _inducing_alpha(zt, yt, params, torch.from_numpy(expansion).to(device), pool, rows_done)
                alpha = torch.where(useful[:, None], alpha, torch.zeros_like(alpha)).cpu()
            lo, hi = _bounds(p, "cpu")
            params = torch.maximum(torch.minimum(params.cpu(), hi), lo)
            log_scale = torch.from_numpy(np.log(scale))
            model.log_lengthscale.copy_(params[:, :p])
            model.log_signal.copy_(params[:, p] + log_scale)  # kernel in coefficient units...
            model.log_additive.copy_(params[:, p + 2] + log_scale)
            model.alpha.copy_((alpha / torch.from_numpy(scale)[:, None]).T)  # ...and α / scale: k α = scale k̃ α̃
            noise = torch.exp(2 * params[:, p + 1]) + _NOISE_FLOOR  # the variance the posterior used
            model.log_noise.copy_(0.5 * torch.log(noise) + log_scale)
        report(total, total)
    elif progress is not None:
        progress(0, 0)
    model.eval()
    return model
