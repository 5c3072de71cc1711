"""What one marginal-likelihood evaluation of a `gp` model costs, three ways, side by side.

    python benchmarks/gp_fit.py DATA TS [--camera left] [--sizes 96,240,480] [--repeats 3] [--threads 1]

DATA is a dataset and TS a texcoord set of it (`python -m mvtex synth DATA --poses 1200`,
`python -m mvtex slide DATA --rig stereo --out TS --subdiv 1`). On the first K training
poses (K = --sizes) of camera `--camera`, with the targets `mvtex train --arch gp` fits (the
first 32 principal components of d, each at unit variance) and every component at the fit's
starting hyperparameters, one negative log marginal likelihood and its gradient for all
components at once is timed for:

    reference  component by component, float64 autograd through a kernel that adds its
               one-dimensional terms coordinate by coordinate (benchmarks/_gp_reference.py)
    mvtex      `mvtex.tsnn.gp`: all components batched, closed-form gradient tile by tile
    gpytorch   GPyTorch batched exact GPs (batch_shape = components): ScaleKernel(RBFKernel
               (ARD)) + ScaleKernel(AdditiveStructureKernel(the same RBFKernel)), Gaussian
               likelihood, ExactMarginalLogLikelihood, autograd; exact Cholesky solves
               (only if gpytorch is installed)

alternating (reference, mvtex, gpytorch, reference, ...) `--repeats` times; the median is
printed with the load average, and the three likelihoods are checked to be the same
number (they are the same function). Prints a Markdown table.
"""

from __future__ import annotations

import argparse
import math
import os
import time
from functools import partial
from pathlib import Path

import numpy as np


def targets(dataset: Path, texcoords: Path, camera: str, k: int, components: int = 32):
    """(z (K,P) standardised poses, y (C,K) unit-variance PCA coefficients) as the fit makes them."""
    from mvtex.data.dataset import load_dataset
    from mvtex.data.texcoords import open_texcoords

    ds = load_dataset(dataset)
    tc = open_texcoords(texcoords, ds.num_vertices)
    poses = [p for p in ds.split["train"] if p in set(tc.poses)][:k]
    x = np.asarray(ds.poses[poses], np.float64)
    d = np.stack([tc.displacement(camera, p) for p in poses]).astype(np.float64).reshape(len(poses), -1)
    z = (x - x.mean(0)) / np.where(x.std(0) > 1e-12, x.std(0), 1.0)
    centred = d - d.mean(0)
    eigval, eigvec = np.linalg.eigh(centred @ centred.T)
    order = np.argsort(eigval)[::-1][:components]
    coef = eigvec[:, order] * np.sqrt(eigval[order])
    return z, (coef / coef.std(0)).T.copy()


def reference_evaluation(z, y, row):
    """Sum over components of the reference's NLL, each with its own autograd backward."""
    import torch
    from _gp_reference import LOG_L_MIN, _kernel

    total = 0.0
    p = z.shape[1]
    for c in range(len(y)):
        q = row.clone().requires_grad_(True)
        a = (_kernel(z, z, q[:p].clamp(LOG_L_MIN, 6.0), q[p].clamp(-6.0, 3.0), q[p + 2].clamp(-8.0, 3.0))
             + (torch.exp(2 * q[p + 1]) + 1e-6) * torch.eye(len(z), dtype=torch.float64))
        chol = torch.linalg.cholesky(a)
        alpha = torch.cholesky_solve(y[c][:, None], chol)[:, 0]
        nll = 0.5 * (y[c] @ alpha) + torch.log(torch.diagonal(chol)).sum()
        nll.backward()
        total += float(nll.detach())
    return total


def mvtex_evaluation(z, y, row):
    """One batched evaluation as the fit makes it (its parts on the torch threads' count of
    Python threads, each operation on one thread)."""
    import torch

    from mvtex.tsnn.gp import _objective, _workers

    with _workers("cpu") as pool:
        f, _ = _objective(z, y, pool)(row.expand(len(y), -1).clone(), torch.arange(len(y)))
    return float(f.sum())


def gpytorch_model(z, y, row):
    """A batched GPyTorch model at the hyperparameters `row` ([log ℓ (P), log s, log σ, log t])."""
    import gpytorch
    import torch

    c, k = y.shape
    p = z.shape[1]
    batch = torch.Size([c])
    inputs = z.expand(c, k, p).contiguous()

    class Model(gpytorch.models.ExactGP):
        def __init__(self, likelihood):
            super().__init__(inputs, y, likelihood)
            rbf = gpytorch.kernels.RBFKernel(ard_num_dims=p, batch_shape=batch)
            self.ard = gpytorch.kernels.ScaleKernel(rbf, batch_shape=batch)
            self.additive = gpytorch.kernels.ScaleKernel(gpytorch.kernels.AdditiveStructureKernel(rbf, num_dims=p),
                                                         batch_shape=batch)
            self.mean = gpytorch.means.ZeroMean(batch_shape=batch)

        def forward(self, x):
            return gpytorch.distributions.MultivariateNormal(self.mean(x), self.ard(x) + self.additive(x))

    likelihood = gpytorch.likelihoods.GaussianLikelihood(
        batch_shape=batch, noise_constraint=gpytorch.constraints.GreaterThan(1e-7))
    model = Model(likelihood).double()
    model.ard.base_kernel.lengthscale = torch.exp(row[:p]).expand(c, 1, p)
    model.ard.outputscale = torch.exp(2 * row[p]).expand(c)
    model.additive.outputscale = torch.exp(2 * row[p + 2]).expand(c)
    likelihood.noise = (torch.exp(2 * row[p + 1]) + 1e-6).expand(c, 1)
    model.train()
    likelihood.train()
    return model, gpytorch.mlls.ExactMarginalLogLikelihood(likelihood, model), inputs


def gpytorch_evaluation(model, mll, inputs, y):
    import gpytorch

    model.zero_grad()
    k = y.shape[1]
    with gpytorch.settings.max_cholesky_size(100000):
        loss = -(mll(model(inputs), y) * k).sum()  # GPyTorch divides the log likelihood by K
    loss.backward()
    return float(loss) - 0.5 * k * math.log(2 * math.pi) * len(y)  # without the constant


def main() -> None:
    import warnings

    import torch

    from mvtex.tsnn.gp import _start

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("texcoords", type=Path)
    parser.add_argument("--camera", default="left")
    parser.add_argument("--sizes", default="96,240,480")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    try:
        import gpytorch  # noqa: F401

        warnings.filterwarnings("ignore", category=DeprecationWarning)  # AdditiveStructureKernel
        have_gpytorch = True
    except ImportError:
        have_gpytorch = False
    print("| training poses | components | reference ms | mvtex ms | gpytorch ms | reference / mvtex | "
          "gpytorch / mvtex | NLL (same for all) | load |")
    print("|---|---|---|---|---|---|---|---|---|")
    for k in [int(s) for s in args.sizes.split(",")]:
        z_np, y_np = targets(args.dataset, args.texcoords, args.camera, k)
        z, y = torch.from_numpy(z_np), torch.from_numpy(y_np)
        row = _start(1, z.shape[1], "cpu")[0]
        times: dict[str, list[float]] = {"reference": [], "mvtex": [], "gpytorch": []}
        values: dict[str, float] = {}
        gpy = gpytorch_model(z, y, row) if have_gpytorch else None
        load = os.getloadavg()[0]
        runs = {"reference": partial(reference_evaluation, z, y, row), "mvtex": partial(mvtex_evaluation, z, y, row)}
        if gpy is not None:
            runs["gpytorch"] = partial(gpytorch_evaluation, *gpy, y)
        for name, fn in runs.items():  # warm-up
            values[name] = fn()
        for _ in range(args.repeats):
            for name, fn in runs.items():
                t0 = time.perf_counter()
                values[name] = fn()
                times[name].append(time.perf_counter() - t0)
        load = f"{load:.1f}-{os.getloadavg()[0]:.1f}"
        spread = max(values.values()) - min(values.values())
        if spread > 1e-6 * abs(values["mvtex"]):
            raise SystemExit(f"the likelihoods differ at K={k}: {values}")
        ms = {name: 1e3 * float(np.median(v)) if v else math.nan for name, v in times.items()}
        print(f"| {k} | {len(y)} | {ms['reference']:.0f} | {ms['mvtex']:.0f} | {ms['gpytorch']:.0f} | "
              f"{ms['reference'] / ms['mvtex']:.1f} | {ms['gpytorch'] / ms['mvtex']:.1f} | {values['mvtex']:.3f} | "
              f"{load} |", flush=True)


if __name__ == "__main__":
    main()
