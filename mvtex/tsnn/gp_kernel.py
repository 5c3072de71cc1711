"""The kernel of `gp` (mvtex.tsnn.gp) and its log marginal likelihood, batched over many GPs.

    k(θ, θ') = s² exp(-½ Σ_i r_i²) + t² Σ_i exp(-½ r_i²),   r_i = (θ_i - θ'_i) / ℓ_i

on standardised poses, one parameter row [log ℓ (P), log s, log σ, log t] per GP (σ the
noise std). `negative_log_likelihood` evaluates R of them together: a batched Cholesky
factorisation of the (R,K,K) covariances and the closed-form gradient
½ tr((A⁻¹ - ααᵀ) ∂A/∂θ), summed tile by tile over the upper triangle of pose pairs, so no
autograd graph is kept and the (R,K,K,P) array of one-dimensional terms never exists
whole. `loo_residuals` is the closed-form leave-one-out of a GP.
"""

from __future__ import annotations

import math

import torch

# Shortest lengthscale, in training standard deviations of the pose coordinate: shorter ones
# only fit noise (a few hundred poses cannot resolve them in a dozen dimensions).
LOG_L_MIN = math.log(0.3)


NOISE_FLOOR = 1e-6  # noise variance floor (y has unit variance): keeps the covariance well conditioned


DEVICE_SCALE = 16  # larger tiles and parts on CUDA: fewer, larger kernels


TILE_ELEMENTS = 2 ** 18  # (rows, tile, tile, P) temporaries of the kernel: 2 MB of float64, cache-sized


def tiles(n: int, size: int) -> list[tuple[int, int]]:
    """[start, stop) ranges of `size` covering range(n)."""
    return [(i, min(i + size, n)) for i in range(0, n, size)]


def tile_size(rows: int, p: int, device) -> int:
    """Poses per side of a tile of R = `rows` kernels in P dimensions (`TILE_ELEMENTS` per temporary)."""
    budget = TILE_ELEMENTS * (1 if torch.device(device).type == "cpu" else DEVICE_SCALE)
    return max(8, int(math.sqrt(budget / max(1, rows * p))))


def tile_terms(a: torch.Tensor, b: torch.Tensor, half: torch.Tensor):
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
    size = tile_size(rows, p, a.device)
    half = -0.5 * torch.exp(-2 * log_lengthscale)
    s2, t2 = torch.exp(2 * log_signal)[:, None, None], torch.exp(2 * log_additive)[:, None, None]
    out = torch.empty(rows, len(a), len(b), dtype=a.dtype, device=a.device)
    for i0, i1 in tiles(len(a), size):
        for j0, j1 in tiles(len(b), size):
            _, ard, additive, _ = tile_terms(a[i0:i1], b[j0:j1], half)
            out[:, i0:i1, j0:j1] = s2 * ard + t2 * additive
    return out


def kernel(a: torch.Tensor, b: torch.Tensor, log_lengthscale: torch.Tensor, log_signal: torch.Tensor,
            log_additive: torch.Tensor) -> torch.Tensor:
    """The kernel matrix (len(a), len(b)) of one set of hyperparameters (see `kernel_matrix`)."""
    return kernel_matrix(a, b, log_lengthscale[None], log_signal.reshape(1), log_additive.reshape(1))[0]


def loo_residuals(inverse: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Leave-one-out residuals y_i - E[y_i | y_-i] of a GP in closed form (Rasmussen &
    Williams, eq. 5.12): [A⁻¹y]_i / [A⁻¹]_ii, with A = K + σ²I and `inverse` = A⁻¹ (...,K,K)
    (batched over leading dimensions; y (...,K))."""
    return (inverse @ y[..., None])[..., 0] / torch.diagonal(inverse, dim1=-2, dim2=-1)


def bounds(p: int, device) -> tuple[torch.Tensor, torch.Tensor]:
    """Lower and upper bounds of a parameter row [log ℓ (P), log s, log σ, log t]."""
    inf = math.inf
    lo = torch.tensor([LOG_L_MIN] * p + [-6.0, -inf, -8.0], dtype=torch.float64, device=device)
    hi = torch.tensor([6.0] * p + [3.0, inf, 3.0], dtype=torch.float64, device=device)
    return lo, hi


def covariance(z: torch.Tensor, params: torch.Tensor) -> torch.Tensor:
    """A = K + (σ² + floor) I of R parameter rows (R, P+3) (already within bounds): (R,K,K).
    Only the tiles on and above the diagonal are computed; the others are their transposes."""
    rows, p = len(params), z.shape[1]
    size = tile_size(rows, p, z.device)
    half = -0.5 * torch.exp(-2 * params[:, :p])
    s2, t2 = torch.exp(2 * params[:, p])[:, None, None], torch.exp(2 * params[:, p + 2])[:, None, None]
    a = torch.empty(rows, len(z), len(z), dtype=z.dtype, device=z.device)
    pairs = tiles(len(z), size)
    for n, (i0, i1) in enumerate(pairs):
        for j0, j1 in pairs[n:]:
            _, ard, additive, _ = tile_terms(z[i0:i1], z[j0:j1], half)
            a[:, i0:i1, j0:j1] = s2 * ard + t2 * additive
            if j0 != i0:
                a[:, j0:j1, i0:i1] = a[:, i0:i1, j0:j1].transpose(1, 2)
    a.diagonal(dim1=1, dim2=2).add_((torch.exp(2 * params[:, p + 1]) + NOISE_FLOOR)[:, None])
    return a


def negative_log_likelihood(z: torch.Tensor, y: torch.Tensor, params: torch.Tensor) -> tuple[torch.Tensor, ...]:
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
    lo, hi = bounds(p, z.device)
    inside = (params >= lo) & (params <= hi)
    q = torch.maximum(torch.minimum(params, hi), lo)
    a = covariance(z, q)
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
    pairs = tiles(len(z), tile_size(rows, p, z.device))
    for n, (i0, i1) in enumerate(pairs):
        for j0, j1 in pairs[n:]:
            twice = 1.0 if j0 == i0 else 2.0  # an off-diagonal tile stands for its transpose too
            w = inverse[:, i0:i1, j0:j1] - alpha[:, i0:i1, None] * alpha[:, None, j0:j1]
            d2, ard, additive, e = tile_terms(z[i0:i1], z[j0:j1], half)
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
