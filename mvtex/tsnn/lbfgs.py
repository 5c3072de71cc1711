"""Many independent smooth minimisations at once: one L-BFGS per row, evaluated together.

`minimise` runs B problems x_b ∈ R^n side by side. Each row has its own L-BFGS history,
its own backtracking line search (Armijo, quadratic interpolation) and its own stopping
test, so a row's path is the one it would take alone; what the rows share is the call of
the objective, which evaluates every row still running in one batched computation (a
stack of Cholesky factorisations, say). A row that has stopped costs nothing further.

Why not one optimiser on the sum of the objectives: the sum's Hessian is block diagonal,
but one L-BFGS history mixes the blocks, one line search gives every row the same step,
and one stopping test keeps converged rows iterating until the slowest has finished.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

Objective = Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]]


@dataclass(frozen=True)
class Result:
    """What `minimise` found, row by row.

    Attributes:
        x: (B,n) the last accepted point of each row.
        f: (B,) its objective (inf where the objective was never finite).
        iterations: (B,) int64 accepted steps.
        evaluations: total rows evaluated, summed over calls of the objective.
    """

    x: torch.Tensor
    f: torch.Tensor
    iterations: torch.Tensor
    evaluations: int


def _direction(g: torch.Tensor, s: torch.Tensor, y: torch.Tensor, rho: torch.Tensor) -> torch.Tensor:
    """-H g by the L-BFGS two-loop recursion, row by row (Nocedal & Wright, alg. 7.4).

    Args:
        g: (b,n) gradients. s, y: (b,m,n) step and gradient differences, newest last;
            unused slots are zero with rho 0, so they change nothing. rho: (b,m) 1/(s·y).
    """
    m = s.shape[1]
    q = g.clone()
    a = torch.zeros_like(rho)
    for i in range(m - 1, -1, -1):
        a[:, i] = rho[:, i] * (s[:, i] * q).sum(1)
        q -= a[:, i, None] * y[:, i]
    yy = (y[:, -1] * y[:, -1]).sum(1)
    gamma = torch.where(rho[:, -1] > 0, 1.0 / (rho[:, -1] * yy).clamp_min(1e-300), torch.ones_like(yy))
    r = gamma[:, None] * q
    for i in range(m):
        b = rho[:, i] * (y[:, i] * r).sum(1)
        r += (a[:, i] - b)[:, None] * s[:, i]
    return -r


def minimise(objective: Objective, x0: torch.Tensor, iterations: int, lower: torch.Tensor | None = None,
             upper: torch.Tensor | None = None, history: int = 20, tolerance_grad: float = 1e-7,
             tolerance_change: float = 1e-10, max_backtracks: int = 20,
             progress: Callable[[int, int], None] | None = None) -> Result:
    """Minimise B independent objectives with one L-BFGS each, evaluated together.

    Bounds are kept by projection: a coordinate at a bound whose gradient points outwards
    is held there (it takes no part in the quasi-Newton direction), every trial point is
    clamped into the box, and the sufficient decrease is measured along the step taken.
    A row stops after `iterations` accepted steps, when its largest free gradient entry is
    at most `tolerance_grad`, when a step changes its objective or its point by less than
    `tolerance_change`, or when `max_backtracks` shorter steps find no decrease. A trial
    point whose objective is not finite (a covariance that is not positive definite)
    counts as no decrease. Deterministic: plain tensor arithmetic, no randomness.

    Args:
        objective: (x (b,n), rows (b,) int64 indices into 0..B-1) -> (f (b,), g (b,n));
            f may be inf where the objective is undefined (g is then ignored).
        x0: (B,n) float starting points (clamped into the bounds).
        iterations: most accepted steps per row.
        lower, upper: (n,) bounds (±inf for none); None: unbounded.
        history: L-BFGS memory (pairs of steps and gradient changes kept).
        progress: called after every round of trial points with (steps done, B *
            iterations), where a row that has stopped counts as all its steps done; it
            reaches B * iterations when every row has stopped.

    Returns:
        `Result`.
    """
    b, n = x0.shape
    inf = torch.full((n,), torch.inf, dtype=x0.dtype, device=x0.device)
    lower = -inf if lower is None else lower.to(x0)
    upper = inf if upper is None else upper.to(x0)

    def free(x, g):  # the gradient without the coordinates held at a bound
        held = ((x <= lower) & (g > 0)) | ((x >= upper) & (g < 0))
        return torch.where(held, torch.zeros_like(g), g)

    rows = torch.arange(b, device=x0.device)
    x = torch.maximum(torch.minimum(x0, upper), lower)
    f, g = objective(x, rows)
    evaluations = b
    s = torch.zeros(b, history, n, dtype=x.dtype, device=x.device)
    y = torch.zeros_like(s)
    rho = torch.zeros(b, history, dtype=x.dtype, device=x.device)
    done = torch.zeros(b, dtype=torch.int64, device=x.device)
    backtracks = torch.zeros_like(done)
    g = torch.where(torch.isfinite(f)[:, None], g, torch.zeros_like(g))
    d = -free(x, g)
    active = torch.isfinite(f) & (d.abs().amax(1) > tolerance_grad) & (iterations > 0)
    t = torch.clamp(1.0 / d.abs().sum(1).clamp_min(1e-300), max=1.0)  # first step: a unit change at most

    def report() -> None:
        if progress is not None:
            steps = torch.where(active, done, torch.full_like(done, iterations))
            progress(int(steps.clamp_max(iterations).sum()), b * iterations)

    report()
    while bool(active.any()):
        report()
        idx = active.nonzero()[:, 0]
        trial = torch.maximum(torch.minimum(x[idx] + t[idx, None] * d[idx], upper), lower)
        f_trial, g_trial = objective(trial, idx)
        evaluations += len(idx)
        step = trial - x[idx]
        decrease = (g[idx] * step).sum(1)
        accept = torch.isfinite(f_trial) & (f_trial <= f[idx] + 1e-4 * decrease) & (decrease < 0)
        # Rejected: a shorter step, the minimiser of the quadratic through f, f' and f(t),
        # kept within [0.1 t, 0.5 t] (a quarter when the trial point is undefined).
        r = idx[~accept]
        if len(r):
            tr, fr, gtd = t[r], f_trial[~accept], decrease[~accept] / t[r]
            curvature = 2 * (fr - f[r] - gtd * tr)
            quadratic = -gtd * tr * tr / torch.where(curvature > 0, curvature, torch.ones_like(curvature))
            shorter = torch.where(torch.isfinite(fr) & (curvature > 0),
                                  torch.minimum(torch.maximum(quadratic, 0.1 * tr), 0.5 * tr), 0.25 * tr)
            t[r] = shorter
            backtracks[r] += 1
            active[r[(backtracks[r] > max_backtracks) | ~(decrease[~accept] < 0)]] = False
        a = idx[accept]
        if not len(a):
            report()
            continue
        step = step[accept]
        change = g_trial[accept] - g[a]
        sy = (step * change).sum(1)
        keep = sy > 1e-10 * (change * change).sum(1).clamp_min(1e-300)  # curvature: H stays positive definite
        k = a[keep]
        s[k] = torch.cat([s[k, 1:], step[keep, None]], 1)
        y[k] = torch.cat([y[k, 1:], change[keep, None]], 1)
        rho[k] = torch.cat([rho[k, 1:], (1.0 / sy[keep])[:, None]], 1)
        f_change = (f[a] - f_trial[accept]).abs()
        x[a], f[a], g[a] = trial[accept], f_trial[accept], g_trial[accept]
        done[a] += 1
        backtracks[a] = 0
        g_free = free(x[a], g[a])
        active[a] = ((done[a] < iterations) & (g_free.abs().amax(1) > tolerance_grad)
                     & (f_change >= tolerance_change) & (step.abs().amax(1) >= tolerance_change))
        d[a] = torch.where(g_free == 0, torch.zeros_like(g_free), _direction(g_free, s[a], y[a], rho[a]))
        uphill = a[(g_free * d[a]).sum(1) >= 0]  # restart from the gradient if the direction does not descend
        if len(uphill):
            s[uphill], y[uphill], rho[uphill] = 0.0, 0.0, 0.0
            d[uphill] = -free(x[uphill], g[uphill])
        t[a] = torch.where(rho[a, -1] > 0, torch.ones_like(t[a]),
                           torch.clamp(1.0 / d[a].abs().sum(1).clamp_min(1e-300), max=1.0))
        report()
    return Result(x=x, f=f, iterations=done, evaluations=evaluations)
