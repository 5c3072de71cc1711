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

The fit. The C likelihoods are independent, so they are evaluated together, with their
closed-form gradients (`mvtex.tsnn.gp_kernel`). Each component keeps its own L-BFGS (`mvtex.tsnn.lbfgs`: its own history, line
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
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch
from torch import nn

from mvtex.tsnn.gp_kernel import (
    DEVICE_SCALE,
    NOISE_FLOOR,
    bounds,
    covariance,
    kernel,
    kernel_matrix,
    loo_residuals,
    negative_log_likelihood,
)
from mvtex.tsnn.lbfgs import minimise
from mvtex.tsnn.modeldir import IntegerConfig
from mvtex.tsnn.pca import evenly_spaced, pose_pca_counted, residual_var

MAX_TRAIN = 2000  # training poses an exact GP is fitted on (O(K^3) time, O(K^2) memory)


# Above MAX_TRAIN training poses the posterior mean is that of the subset-of-regressors
# approximation on INDUCING_POSES evenly spaced training poses (O(K M^2) time, O(K M) memory
# per component): every training pose informs the prediction, and the model keeps the same
# form (a kernel expansion on M poses).
INDUCING_POSES = MAX_TRAIN


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


_PART_ROWS = 8  # rows of one part of a batched likelihood evaluation (see `_parts`)


_PART_ELEMENTS = 2 ** 23  # (rows, K, K) float64 arrays of one part: 64 MB each


@dataclass(frozen=True)
class GPConfig(IntegerConfig):
    """Shape of a `PoseGP`.

    Attributes:
        pose_dim: P, length of the pose vector.
        num_vertices: n', vertices the displacements are predicted at.
        num_train: K, poses the posterior mean is expanded on: the training poses (at most
            `MAX_TRAIN`), or the inducing poses of a fit on more training poses.
        components: C, principal components of d modelled (each by its own GP).
        channels: values per vertex: 2 for displacements d (a per-camera model), 3 for
            the geometry corrector's 3-D residual (`mvtex.tsnn.corrector`).
    """

    ARCH = "gp"

    pose_dim: int
    num_vertices: int
    num_train: int
    components: int
    channels: int = 2

    def validate(self) -> None:
        if self.pose_dim < 1 or self.num_vertices < 1 or self.num_train < 1:
            raise ValueError("pose_dim, num_vertices and num_train must be positive")
        if not 0 <= self.components <= min(MAX_COMPONENTS, self.num_train):
            raise ValueError(f"components must be in 0..min({MAX_COMPONENTS}, num_train), got {self.components}")
        if self.num_train > MAX_TRAIN:
            raise ValueError(f"num_train is at most {MAX_TRAIN}, got {self.num_train}")
        if self.channels not in (2, 3):
            raise ValueError(f"channels must be 2 or 3, got {self.channels}")



class PoseGP(nn.Module):
    """Posterior mean of per-component GPs: pose (B,P) -> d (B,n',c) float32 (c =
    `GPConfig.channels`: 2 for d); and its predictive standard deviation per vertex
    (`predictive_std`).

    Buffers (float64): pose_mean/pose_std (P,), inputs (K,P) standardised training poses,
    log_lengthscale (C,P), log_signal (C,), log_additive (C,), alpha (K,C), basis (C,c·n'), mean (c·n',);
    output_scale (1.0, for the model directory's record); for the predictive variance,
    log_noise (C,) the log noise std of each component and residual_var (c·n',) the mean
    square of what the C components leave of the training displacements (the PCA
    truncation), both NaN in a model stored without them (it reports no uncertainty).
    """

    per_vertex = True  # predicts d at the vertices, not an atlas image

    # Buffers a stored model may lack (one written before they existed): NaN then.
    optional_buffers = ("log_noise", "residual_var")

    pose_mean: torch.Tensor
    pose_std: torch.Tensor
    inputs: torch.Tensor
    log_lengthscale: torch.Tensor
    log_signal: torch.Tensor
    log_additive: torch.Tensor
    alpha: torch.Tensor
    basis: torch.Tensor
    mean: torch.Tensor
    output_scale: torch.Tensor
    log_noise: torch.Tensor
    residual_var: torch.Tensor

    def __init__(self, config: GPConfig):
        super().__init__()
        config.validate()
        self.config = config
        k, p, c, n = config.num_train, config.pose_dim, config.components, config.num_vertices * config.channels
        f64 = torch.float64
        self.register_buffer("pose_mean", torch.zeros(p, dtype=f64))
        self.register_buffer("pose_std", torch.ones(p, dtype=f64))
        self.register_buffer("inputs", torch.zeros(k, p, dtype=f64))
        self.register_buffer("log_lengthscale", torch.zeros(c, p, dtype=f64))
        self.register_buffer("log_signal", torch.zeros(c, dtype=f64))
        self.register_buffer("log_additive", torch.zeros(c, dtype=f64))
        self.register_buffer("alpha", torch.zeros(k, c, dtype=f64))
        self.register_buffer("basis", torch.zeros(c, n, dtype=f64))
        self.register_buffer("mean", torch.zeros(n, dtype=f64))
        self.register_buffer("output_scale", torch.tensor(1.0))
        self.register_buffer("log_noise", torch.full((c,), math.nan, dtype=f64))
        self.register_buffer("residual_var", torch.full((n,), math.nan, dtype=f64))
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
                a = kernel(self.inputs, self.inputs, self.log_lengthscale[c], self.log_signal[c], self.log_additive[c])
                a.diagonal().add_(torch.exp(2 * self.log_noise[c]))
                factors.append(torch.linalg.cholesky(a))
            self._factors = (key, factors)
        return self._factors[1]

    def predictive_std(self, poses: torch.Tensor) -> torch.Tensor | None:
        """Predictive standard deviation of d per vertex, (B,n') float64 in d's units (uv;
        meters for the geometry corrector): the root of the expected squared length of d's
        error, sqrt(var_u + var_v) (sqrt(var_x + var_y + var_z) for 3 channels).

        Per component c, the GP's predictive variance of a new pose's coefficient,
        k_c(θ,θ) - k_c(θ,Θ) (K_c + σ_c² I)⁻¹ k_c(Θ,θ) + σ_c² (the coefficients of the
        training displacements are noisy observations, and so are a new pose's); a component
        predicted as 0 (α_c = 0) has its prior variance k_c(θ,θ) + σ_c². The components are
        independent, so var(d_j) = Σ_c var_c basis_cj², plus residual_var_j, what the
        truncated components left of the training displacements (`vertex_std`). None when
        the model holds no noise levels (`has_uncertainty`).
        """
        var = self.coefficient_variance(poses)
        return None if var is None else self.vertex_std(var)

    def vertex_std(self, var: torch.Tensor) -> torch.Tensor:
        """Per-vertex standard deviation (B,n') float64 from independent coefficient
        variances var (B,C): sqrt(Σ_channels (var @ basis² + residual_var))."""
        per_coordinate = var.to(torch.float64) @ self.basis.square() + self.residual_var  # (B,c·n')
        return per_coordinate.reshape(len(var), -1, self.config.channels).sum(-1).sqrt()

    def coefficient_variance(self, poses: torch.Tensor) -> torch.Tensor | None:
        """The predictive variance (B,C) float64 of each component's coefficient at poses
        (B,P) (see `predictive_std`); None without noise levels (`has_uncertainty`)."""
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
        return var

    def coefficients(self, poses: torch.Tensor) -> torch.Tensor:
        """The posterior mean (B,C) float64 of each component's coefficient at poses (B,P)."""
        z = (poses.to(torch.float64) - self.pose_mean) / self.pose_std
        k = kernel_matrix(z, self.inputs, self.log_lengthscale, self.log_signal, self.log_additive)  # (C,B,K)
        return torch.einsum("cbk,kc->bc", k, self.alpha)

    def values(self, coefficients: torch.Tensor) -> torch.Tensor:
        """Per-vertex values (B,n',c) float64 of coefficients (B,C): mean + coefficients · basis."""
        d = self.mean + coefficients.to(torch.float64) @ self.basis
        return d.reshape(len(coefficients), -1, self.config.channels)

    def forward(self, poses: torch.Tensor) -> torch.Tensor:
        return self.values(self.coefficients(poses)).to(torch.float32)

    def relevance(self) -> np.ndarray:
        """(C,P) inverse lengthscales: how much each pose coordinate moves each mode."""
        return torch.exp(-self.log_lengthscale).cpu().numpy()


def _parts(rows: int, k: int, device) -> list[slice]:
    """Consecutive parts of a batch of rows on K poses: on the CPU at most `_PART_ROWS` rows,
    and a few (rows,K,K) arrays within `_PART_ELEMENTS` (on CUDA, `DEVICE_SCALE` times
    that, and rows without a limit). The split depends on the batch alone, never on the
    number of threads, so neither do a row's bits."""
    if torch.device(device).type == "cpu":
        size = max(1, min(_PART_ROWS, _PART_ELEMENTS // (k * k)))
    else:
        size = max(1, _PART_ELEMENTS * DEVICE_SCALE // (k * k))
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
        parts = _map(pool, lambda part: negative_log_likelihood(z, y[rows[part]], x[part]),
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

    lo, hi = bounds(z.shape[1], z.device)
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
               done: Callable[[int], None] | None = None, out_of_sample: bool = False):
    """α = A⁻¹y (C,K) of C GPs on every pose; 0 for a component whose leave-one-out error
    is no better than predicting 0. `done(rows)` is called as each part of the rows is done.
    With `out_of_sample`, also each pose's leave-one-out prediction and its noisy variance
    (C,K) (R&W eq. 5.12: y_i - [A⁻¹y]_i / [A⁻¹]_ii, 1 / [A⁻¹]_ii): (α, mean, variance)."""
    lo, hi = bounds(z.shape[1], z.device)
    q = torch.maximum(torch.minimum(params, hi), lo)

    def part_alpha(part: slice) -> torch.Tensor:
        chol, info = torch.linalg.cholesky_ex(covariance(z, q[part]))
        if bool((info != 0).any()):
            raise ValueError("no Gaussian-process fit: the covariance of all training poses is singular")
        inverse = torch.cholesky_inverse(chol)
        a = (inverse @ y[part, :, None])[:, :, 0]
        residuals = loo_residuals(inverse, y[part])
        useless = ~(residuals.square().mean(1) < y[part].square().mean(1))
        if done is not None:
            done(part.stop - part.start)
        a = torch.where(useless[:, None], torch.zeros_like(a), a)
        if not out_of_sample:
            return a
        return a, y[part] - residuals, 1.0 / torch.diagonal(inverse, dim1=1, dim2=2)

    with _workers(z.device) if pool is None else contextlib.nullcontext(pool) as threads:
        out = _map(threads, part_alpha, _parts(len(y), len(z), z.device))
    return tuple(torch.cat([o[i] for o in out]) for i in range(3)) if out_of_sample else torch.cat(out)


def _inducing_alpha(z: torch.Tensor, y: torch.Tensor, params: torch.Tensor, inducing: torch.Tensor,
                    pool=None, done: Callable[[int], None] | None = None, folds: int = 0):
    """Subset-of-regressors posterior mean weights (C,M) of C GPs on all K poses z (K,P),
    expanded on the M poses z[inducing]: α = (σ² K_mm + K_mk K_km)⁻¹ K_mk y (Rasmussen &
    Williams, eq. 8.14), computed stably as L⁻ᵀ (σ²I + AAᵀ)⁻¹ A y with K_mm = LLᵀ and
    A = L⁻¹ K_mk. The prediction k(θ, Z_m) α is then the exact GP's when M = K.
    `done(rows)` is called as each part of the rows is done.

    With `folds` > 0, also each pose's prediction by the model fitted without its fold (every
    `folds`-th pose), same hyperparameters, and its noisy variance (C,K): the sparse GP is
    Bayesian linear regression on the features A (weights of prior N(0, I)), so with
    S = σ²I + AAᵀ and the hat matrix H = AᵀS⁻¹A the refit's prediction of fold f is
    y_f - (I - H_ff)⁻¹ (y_f - (Hy)_f), its variance σ² diag((I - H_ff)⁻¹) (Woodbury); S's
    factor is the fit's own. Returns (α, mean, variance) then."""
    lo, hi = bounds(z.shape[1], z.device)
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
        noise = torch.exp(2 * rows[:, p + 1]) + NOISE_FLOOR
        b = torch.linalg.cholesky(a @ a.transpose(1, 2) + noise[:, None, None] * eye)
        c = torch.cholesky_solve((a @ y[part, :, None]), b)
        alpha = torch.linalg.solve_triangular(chol.transpose(1, 2), c, upper=True)[:, :, 0]
        if folds:
            alpha = (alpha, *_fold_predictions(torch.linalg.solve_triangular(b, a, upper=False), y[part], noise,
                                               folds))
        if done is not None:
            done(part.stop - part.start)
        return alpha

    size = max(1, min(_PART_ROWS, _PART_ELEMENTS // (m * len(z))))
    parts = [slice(i, min(i + size, len(y))) for i in range(0, len(y), size)]
    with _workers(z.device) if pool is None else contextlib.nullcontext(pool) as threads:
        out = _map(threads, part_alpha, parts)
    return tuple(torch.cat([o[i] for o in out]) for i in range(3)) if folds else torch.cat(out)


def _fold_predictions(v: torch.Tensor, y: torch.Tensor, noise: torch.Tensor, folds: int
                      ) -> tuple[torch.Tensor, torch.Tensor]:
    """Fold-out predictions and variances (R,K) of sparse GPs from v = S^-1/2 A (R,M,K)
    (`_inducing_alpha`), targets y (R,K), noise variances (R,)."""
    fitted = (v.transpose(1, 2) @ (v @ y[:, :, None]))[:, :, 0]  # Hy
    mean, var = torch.empty_like(y), torch.empty_like(y)
    for f in range(folds):
        rows = torch.arange(f, y.shape[1], folds, device=y.device)
        if not len(rows):
            continue
        vf = v[:, :, rows]
        inverse = torch.linalg.inv(torch.eye(len(rows), dtype=y.dtype, device=y.device) - vf.transpose(1, 2) @ vf)
        mean[:, rows] = y[:, rows] - (inverse @ (y[:, rows] - fitted[:, rows])[:, :, None])[:, :, 0]
        var[:, rows] = noise[:, None] * torch.diagonal(inverse, dim1=1, dim2=2)
    return mean, var


def fit_pose_gp(poses: np.ndarray, d, components: int = 32, iterations: int = 40,
                progress: Callable[[int, int], None] | None = None, device: str | torch.device = "cpu",
                inducing: int = INDUCING_POSES) -> PoseGP:
    """Fit a `PoseGP` to training displacements.

    Args:
        poses: (K,P) training pose vectors.
        d: (K,n',c) their displacements (c = 2; 3-D residuals, c = 3, for the geometry
            corrector), an array or anything `d[rows]` reads rows of (`pose_pca`).
        components: principal components modelled (fewer when K - 1 is smaller).
        iterations: most L-BFGS iterations per component. 40: on the built-in shirt (480
            training poses, camera left) the test poses' displacement error is within 0.01 %
            of that with 60 iterations, and the fit takes a third less time.
        progress: called with (steps done, steps) as the fit goes: the chunks of
            256 training poses read (`pose_pca`), the L-BFGS steps of every component (a
            stopped component counts as all its steps), then one step per
            component for the posterior (two above `inducing` training poses: the
            leave-one-out test on the hyperparameters' poses, then the inducing posterior).
        device: where the likelihoods are evaluated; the model comes back on the CPU.
        inducing: above this many training poses (at most `MAX_TRAIN`), the posterior mean
            is the subset-of-regressors one on this many evenly spaced training poses;
            up to it, the exact one on every training pose.
    """
    if not 1 <= inducing <= MAX_TRAIN:
        raise ValueError(f"inducing must be in 1..{MAX_TRAIN}, got {inducing}")
    pca, reads = pose_pca_counted(poses, d, components, progress)
    _, _, _, mean_d, basis, coef = pca
    return fit_components(pca, residual_var(d, mean_d, basis, coef), int(np.shape(d)[2]), iterations, progress,
                          device, inducing, reads)[0]


def fit_components(pca: tuple, residual: np.ndarray, channels: int, iterations: int = 40,
                   progress: Callable[[int, int], None] | None = None, device: str | torch.device = "cpu",
                   inducing: int = INDUCING_POSES, reads: int = 0, out_of_sample: int = 0
                   ) -> tuple[PoseGP, tuple[np.ndarray, np.ndarray] | None]:
    """The GPs of `fit_pose_gp` on principal components already taken.

    Args:
        pca: what `mvtex.tsnn.pca.pose_pca` returns (x, mean_x, std_x, mean_d, basis, coef).
        residual: (c·n',) `mvtex.tsnn.pca.residual_var` of the training values.
        channels: c, values per vertex (2 for d).
        iterations, progress, device, inducing: as `fit_pose_gp`; reads: the progress steps
            already taken by reading the training values.
        out_of_sample: > 0: also every training pose's out-of-sample coefficients, from the
            factorisations the fit makes anyway: the closed-form leave-one-out of an exact
            model, or `out_of_sample`-fold predictions of a sparse one (same hyperparameters).

    Returns:
        the model, and with `out_of_sample` (mean, variance) (K,C) float64 of the
        coefficients (the noisy variance; a component predicted as 0 gives 0 and its prior
        variance), else None.
    """
    if not 1 <= inducing <= MAX_TRAIN:
        raise ValueError(f"inducing must be in 1..{MAX_TRAIN}, got {inducing}")
    x, mean_x, std_x, mean_d, basis, coef = pca
    k, p = x.shape
    exact = k <= inducing
    expansion = np.arange(k) if exact else evenly_spaced(k, inducing)
    z = (x - mean_x) / std_x
    config = GPConfig(pose_dim=p, num_vertices=len(mean_d) // channels, num_train=len(expansion),
                      components=len(basis), channels=channels)
    model = PoseGP(config)
    with torch.no_grad():
        model.pose_mean.copy_(torch.from_numpy(mean_x))
        model.pose_std.copy_(torch.from_numpy(std_x))
        model.inputs.copy_(torch.from_numpy(z[expansion]))
        model.basis.copy_(torch.from_numpy(basis))
        model.mean.copy_(torch.from_numpy(mean_d))
        model.residual_var.copy_(torch.from_numpy(np.asarray(residual, np.float64)))
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
            oos = None
            if exact:
                alpha = _posterior(zt, yt, params, pool, rows_done, out_of_sample=bool(out_of_sample))
                alpha, oos = (alpha[0].cpu(), alpha[1:]) if out_of_sample else (alpha.cpu(), None)
            else:
                # A component is kept if its leave-one-out error on the hyperparameters' poses
                # beats predicting 0 (the exact test, as below MAX_TRAIN).
                useful = _posterior(zt[hyper], yt[:, hyper], params, pool, rows_done).abs().sum(1) > 0
                alpha = _inducing_alpha(zt, yt, params, torch.from_numpy(expansion).to(device), pool, rows_done,
                                        folds=out_of_sample)
                alpha, oos = (alpha[0], alpha[1:]) if out_of_sample else (alpha, None)
                alpha = torch.where(useful[:, None], alpha, torch.zeros_like(alpha)).cpu()
            lo, hi = bounds(p, "cpu")
            params = torch.maximum(torch.minimum(params.cpu(), hi), lo)
            log_scale = torch.from_numpy(np.log(scale))
            model.log_lengthscale.copy_(params[:, :p])
            model.log_signal.copy_(params[:, p] + log_scale)  # kernel in coefficient units...
            model.log_additive.copy_(params[:, p + 2] + log_scale)
            model.alpha.copy_((alpha / torch.from_numpy(scale)[:, None]).T)  # ...and α / scale: k α = scale k̃ α̃
            noise = torch.exp(2 * params[:, p + 1]) + NOISE_FLOOR  # the variance the posterior used
            model.log_noise.copy_(0.5 * torch.log(noise) + log_scale)
            if oos is not None:  # back to coefficient units; a component predicted as 0: its prior
                kept = (model.alpha != 0).any(0)
                prior = (torch.exp(2 * model.log_signal) + p * torch.exp(2 * model.log_additive)
                         + torch.exp(2 * model.log_noise))
                s = torch.from_numpy(scale)
                mean = torch.where(kept[None], oos[0].cpu().T * s, 0.0)
                var = torch.where(kept[None], oos[1].cpu().T * s ** 2, prior[None])
                oos = (mean.numpy(), var.numpy())
        report(total, total)
    else:
        oos = (np.zeros((k, 0)), np.zeros((k, 0))) if out_of_sample else None
        if progress is not None:
            progress(0, 0)
    model.eval()
    return model, oos
