"""The component-by-component `gp` fit that `mvtex.tsnn.gp.fit_pose_gp` is measured against.

Each of the C principal components is fitted alone: float64 autograd through a kernel that
adds its one-dimensional terms coordinate by coordinate, `torch.optim.LBFGS` (strong Wolfe)
from the three starts of `_STARTS` on at most 400 evenly spaced poses, the best refined for
100 iterations on up to ~1,300 poses, then the posterior on all of them with the same
leave-one-out guard. It writes the same `PoseGP` (same buffers), so `train`, `predict` and
`evaluate` treat its models like the library's. `patched()` makes `train` use it.

Used by the benchmark scripts of this folder only.
"""

from __future__ import annotations

import contextlib
import math

import numpy as np

HYPER_POSES = 400
REFINE_ITERATIONS = 100
REFINE_ELEMENTS = 2e7
STARTS = ((1.0, 0.1, -2.0), (4.0, 0.1, -2.0), (1.0, 0.5, 0.0))
LOG_L_MIN = math.log(0.3)


def _kernel(a, b, log_lengthscale, log_signal, log_additive):
    import torch

    scale = torch.exp(-log_lengthscale)
    a, b = a * scale, b * scale
    k = torch.exp(2 * log_signal - 0.5 * torch.cdist(a, b).square())
    additive = torch.zeros_like(k)
    for i in range(a.shape[1]):
        additive = additive + torch.exp(-0.5 * (a[:, i, None] - b[None, :, i]).square())
    return k + torch.exp(2 * log_additive) * additive


def _evenly_spaced(k: int, count: int) -> np.ndarray:
    return np.arange(k) if count >= k else np.unique(np.linspace(0, k - 1, count).round().astype(int))


def _fit_component(z, y, iterations, hyper=None):
    import torch

    p = z.shape[1]
    floor = 1e-6
    zh, yh = (z, y) if hyper is None else (z[hyper], y[hyper])

    def covariance(points, log_l, log_s, log_n, log_a):
        return (_kernel(points, points, log_l.clamp(LOG_L_MIN, 6.0), log_s.clamp(-6.0, 3.0), log_a.clamp(-8.0, 3.0))
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
              for lengthscale, noise, additive in STARTS]
    while starts:
        params = [q.clone().requires_grad_(True) for q in starts.pop(0)]
        optimiser = torch.optim.LBFGS(params, lr=0.5, max_iter=iterations, history_size=20,
                                      line_search_fn="strong_wolfe", tolerance_grad=1e-7, tolerance_change=1e-10)

        def closure():
            optimiser.zero_grad()
            nll = objective(params)
            if nll is None:
                nll = sum(q.sum() for q in params) * 0.0 + 1e30
            nll.backward()
            return nll

        optimiser.step(closure)
        with torch.no_grad():
            nll = objective(params)
        if nll is not None and torch.isfinite(nll) and (best is None or float(nll) < best[0]):
            best = (float(nll), [q.detach() for q in params])
        if not starts and hyper is not None and best is not None:
            refine = _evenly_spaced(len(z), max(len(hyper), int(math.sqrt(REFINE_ELEMENTS / p))))
            zh, yh, hyper, iterations = z[refine], y[refine], None, REFINE_ITERATIONS
            starts, fallback, best = [best[1]], best[1], None
    if best is None and fallback is None:
        raise ValueError("no Gaussian-process fit: the covariance is singular at every start")
    log_l, log_s, log_n, log_a = best[1] if best is not None else fallback
    chol, info = torch.linalg.cholesky_ex(covariance(z, log_l, log_s, log_n, log_a))
    if int(info):
        raise ValueError("no Gaussian-process fit: the covariance of all training poses is singular")
    inverse = torch.cholesky_inverse(chol)
    alpha = inverse @ y
    loo = (inverse @ y) / torch.diagonal(inverse)
    if not float(loo.square().mean()) < float(y.square().mean()):
        alpha = torch.zeros_like(alpha)
    return log_l.clamp(LOG_L_MIN, 6.0), log_s.clamp(-6.0, 3.0), log_a.clamp(-8.0, 3.0), alpha


def fit_pose_gp(poses, d, components=32, iterations=60, progress=None, device="cpu"):
    """The reference fit, with `mvtex.tsnn.gp.fit_pose_gp`'s signature (CPU only)."""
    import torch

    from mvtex.tsnn.gp import GPConfig, PoseGP
    from mvtex.tsnn.pca import pose_pca

    x, mean_x, std_x, mean_d, basis, coef = pose_pca(poses, d, components)
    k, p = x.shape
    model = PoseGP(GPConfig(pose_dim=p, num_vertices=len(mean_d) // 2, num_train=k, components=len(basis)))
    z = torch.from_numpy((x - mean_x) / std_x)
    hyper = None if k <= HYPER_POSES else _evenly_spaced(k, HYPER_POSES)
    with torch.no_grad():
        model.pose_mean.copy_(torch.from_numpy(mean_x))
        model.pose_std.copy_(torch.from_numpy(std_x))
        model.inputs.copy_(z)
        model.basis.copy_(torch.from_numpy(basis))
        model.mean.copy_(torch.from_numpy(mean_d))
    for c in range(len(basis)):
        scale = float(coef[:, c].std()) or 1.0
        log_l, log_s, log_a, alpha = _fit_component(z, torch.from_numpy(coef[:, c] / scale), iterations, hyper)
        with torch.no_grad():
            model.log_lengthscale[c] = log_l
            model.log_signal[c] = log_s + math.log(scale)
            model.log_additive[c] = log_a + math.log(scale)
            model.alpha[:, c] = alpha / scale
        if progress is not None:
            progress(c + 1, len(basis))
    model.eval()
    return model


@contextlib.contextmanager
def patched():
    """Within the block, `mvtex.tsnn.train.train` fits `gp` models with this reference."""
    from mvtex.tsnn import gp

    library = gp.fit_pose_gp
    gp.fit_pose_gp = fit_pose_gp
    try:
        yield
    finally:
        gp.fit_pose_gp = library
