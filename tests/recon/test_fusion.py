"""Fusion with a prior (a corrected set's mesh and its σ): the factors against their closed
form, the prior standing where texcoords are garbage or absent, exact texcoords taken."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import sheet_in_front


def _rmse(a, b):
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))


def test_fusion_factors_are_the_gain_of_two_gaussians_and_gate_outliers():
    """w = σ_p² / (σ_p² + κσ²) written out; a point beyond g √(σ_p² + κσ²) keeps nothing; a
    point of unknown or too large σ keeps nothing; exact texcoords (κ = 0) keep everything."""
    from mvtex.recon.trust import fusion_factors

    rng = np.random.default_rng(0)
    sigma = rng.uniform(0.5e-3, 4e-3, 50)
    prior = rng.uniform(0.5e-3, 4e-3, 50)
    kappa, gate = 0.3, 2.5
    total = prior ** 2 + kappa * sigma ** 2
    length = rng.uniform(0, 4, 50) * np.sqrt(total)  # some beyond the gate, some within
    direction = rng.normal(size=(50, 3))
    delta = direction / np.linalg.norm(direction, axis=1, keepdims=True) * length[:, None]
    sigma[3], sigma[4] = np.inf, 0.2
    w, outlier = fusion_factors(delta, sigma, prior, kappa, gate, max_sigma=0.05)
    expected_out = length > gate * np.sqrt(total)
    expected_out[3] = expected_out[4] = False
    assert np.array_equal(outlier, expected_out) and expected_out.sum() > 5
    keep = ~expected_out
    keep[3] = keep[4] = False
    np.testing.assert_allclose(w[keep], (prior ** 2 / total)[keep], rtol=1e-12)
    assert np.all(w[~keep] == 0)
    w0, out0 = fusion_factors(delta, None, prior, kappa, gate)
    assert np.all(w0 == 1) and not out0.any()
    w1, _ = fusion_factors(delta, sigma, prior, 0.0, gate)
    assert np.all(w1 == 1)


@pytest.mark.parametrize("uncertain", [True, False])
def test_fusion_falls_back_to_the_prior_when_the_texcoords_are_garbage(gl, uncertain):
    """gt is flat, the prior (a corrected mesh) 2.5 mm in front of it with σ_p = 2.5 mm,
    the texcoords garbage: a field several pixels wide, different per camera (reporting a
    small uncertainty, or none). Fused, the prior stands (its RMSE to gt within 2 %, measured
    here against gt; under 3 % of the vertices, a stray point and where its displacement is
    extended, move by more than σ_p / 10), where the same
    texcoords without the prior spoil the mesh. Given the exact texcoords instead, the same fusion recovers gt on the
    triangulated vertices and extends it; without `prior_fill`, the vertices no camera
    sees keep the prior exactly."""
    from dataclasses import replace

    from mvtex.recon.options import ReconOptions
    from mvtex.recon.triangulate import reconstruct

    faces, uv, rest, _, rig, _ = sheet_in_front()
    prior = rest + np.array([0.0, 0.0, 0.0025])
    exact = {}
    for cam in rig:  # closed form: the ray through a prior vertex meets the plane z = 0
        C = cam.center
        s = C[2] / (C[2] - prior[:, 2])
        exact[cam.name] = ((C + s[:, None] * (prior - C))[:, :2] + 0.45) / 0.9
    rng = np.random.default_rng(5)
    garbage = {}
    for name, T in exact.items():
        k = rng.normal(size=(2, 2)) * 12
        phase = rng.uniform(0, 2 * np.pi, 2)
        garbage[name] = T + 0.03 * np.stack([np.sin(uv @ k[0] + phase[0]), np.cos(uv @ k[1] + phase[1])], axis=1)
    std = {c: np.full(len(uv), 1e-3, np.float32) for c in rig.names} if uncertain else None
    prior_sigma = np.full(len(uv), 0.0025)
    options = ReconOptions().for_source("tsnn", prior=True)
    prior_rmse = _rmse(prior, rest)
    fused = reconstruct(uv, prior, faces, uv, garbage, rig, options, uncertainty=std, prior_sigma=prior_sigma)
    plain = reconstruct(uv, prior, faces, uv, garbage, rig, ReconOptions(shrink=0, consensus_scale=4))
    assert plain.triangulated.mean() > 0.2 and _rmse(plain.points, rest) > 1.5 * prior_rmse
    assert fused.triangulated.mean() > 0.2  # the points are there; the fusion leaves them out
    assert abs(_rmse(fused.points, rest) / prior_rmse - 1) < 0.02
    moved = np.linalg.norm(fused.points - prior, axis=1)
    assert (moved > 0.1 * 0.0025).mean() < 0.03 and moved.max() < 0.0025  # a stray point or two, within σ_p
    small = {c: np.full(len(uv), 1e-5, np.float32) for c in rig.names}
    good = reconstruct(uv, prior, faces, uv, exact, rig, options, prior_sigma=prior_sigma, uncertainty=small)
    tri = good.triangulated
    assert tri.mean() > 0.3
    assert _rmse(good.points[tri], rest[tri]) < 0.05 * prior_rmse
    assert _rmse(good.points, rest) < 0.5 * prior_rmse  # the fused displacement extended (prior_fill)
    kept = reconstruct(uv, prior, faces, uv, exact, rig, replace(options, prior_fill=False), prior_sigma=prior_sigma,
                       uncertainty=small)
    unseen = ~kept.triangulated & (kept.num_views == 0)
    assert unseen.sum() > 10 and np.array_equal(kept.points[unseen], prior[unseen])
