"""How far the reconstruction trusts its points: the standard deviations of observations and
points, and the factors their displacements are kept by (docs/reconstruction.md, Trust).

Without a prior (`trust_factors`): each triangulated point's displacement δ from the
inferred mesh is kept by the Wiener factor τ² / (τ² + κσ²), σ the point's standard
deviation, τ² the pose's mean ‖δ‖².

With a prior (`fusion_factors`, a corrected set: its inferred mesh is the geometry
corrector's, with a standard deviation σ_p per vertex): the point and the prior are two
estimates of the vertex, and the fused one keeps σ_p² / (σ_p² + κσ²) of δ (the gain of
the Gaussian update). A point whose δ is implausible under both, ‖δ‖² > g² (σ_p² + κσ²)
(`ReconOptions.prior_gate`), is an outlier and keeps nothing: garbage texcoords leave the
prior as it is.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from mvtex.data.camera import Camera
from mvtex.recon.geometry import camera_arrays, projection_jacobian, reprojection_errors
from mvtex.recon.locate import Hypotheses
from mvtex.recon.options import MIN_SIGMA_PX

# Texcoords without a reported uncertainty: each observation's standard deviation is this
# many times the pose's disagreement between the cameras (`consistency_sigma_px`). Errors
# that the cameras share (a predictor wrong in the same way for every camera) do not show
# as disagreement; the factor was chosen with `ReconOptions.shrink` on held-out poses of
# both built-in garments (docs/reconstruction.md).
CONSISTENCY_INFLATION = 12.0


def observation_sigma_px(hypotheses: Hypotheses, pixels: np.ndarray, points: np.ndarray,
                         cameras: Sequence[Camera]) -> np.ndarray | None:
    """The standard deviation (px) of each chosen observation (n,C) from its hypothesis'
    3-D standard deviation (`Hypotheses.sigma`) seen at the depth of `points` (fx / z), at
    least `MIN_SIGMA_PX`; inf where none was chosen. None when the hypotheses carry no sigma."""
    if hypotheses.sigma is None:
        return None
    n, C = pixels.shape[:2]
    sigma = np.full((n, C), np.inf)
    hv, hc = hypotheses.vertex, hypotheses.camera
    same = np.all(pixels[hv, hc] == hypotheses.pixel, axis=1)
    sigma[hv[same], hc[same]] = hypotheses.sigma[same]
    K, R, t = camera_arrays(cameras)
    z = np.einsum("cj,nj->nc", R[:, 2], np.nan_to_num(points)) + t[None, :, 2]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        px = sigma * K[None, :, 0, 0] / z
    return np.where(np.isfinite(px) & (z > 0), np.maximum(px, MIN_SIGMA_PX), np.inf)


def point_sigma(cameras: Sequence[Camera], points: np.ndarray, weights: np.ndarray, sigma_px: np.ndarray
                ) -> np.ndarray:
    """The standard deviation (m, root of the covariance's trace) of triangulated points
    from independent observation errors of standard deviation sigma_px (n,C): the inverse
    of the Fisher information Σ_c J_cᵀ J_c / σ_c² of the projections. NaN where the
    point is not finite; inf where the observations do not fix it."""
    K, R, t = camera_arrays(cameras)
    X = np.nan_to_num(points)
    y = np.einsum("cij,nj->nci", R, X) + t[None]
    J = np.nan_to_num(projection_jacobian(K, R, y))  # (n,C,2,3)
    with np.errstate(divide="ignore"):
        w = np.where((weights > 0) & np.isfinite(sigma_px), 1.0 / np.maximum(sigma_px, 1e-300) ** 2, 0.0)
    info = np.einsum("nc,ncki,nckj->nij", w, J, J)
    out = np.full(len(X), np.inf)
    ok = np.linalg.det(info) > 0
    if ok.any():
        cov = np.linalg.inv(info[ok])
        out[ok] = np.sqrt(np.maximum(np.trace(cov, axis1=1, axis2=2), 0.0))
    out[~np.all(np.isfinite(points), axis=1)] = np.nan
    return out


def consistency_sigma_px(cameras: Sequence[Camera], points: np.ndarray, pixels: np.ndarray,
                         weights: np.ndarray) -> float:
    """The standard deviation (px, per image coordinate) of the observations of one pose,
    from how well the cameras agree: the squared reprojection errors of the triangulated
    points summed over the pose, over their degrees of freedom (2 per observation, less 3
    per point). For texcoords without a reported uncertainty. NaN without a point seen
    more than twice over."""
    used = np.asarray(weights) > 0
    views = used.sum(axis=1)
    rows = np.flatnonzero((views >= 2) & np.all(np.isfinite(points), axis=1))
    if not len(rows):
        return math.nan
    err = reprojection_errors(cameras, points[rows], pixels[rows])
    err2 = np.where(used[rows], np.nan_to_num(err, nan=0.0) ** 2, 0.0).sum()
    dof = float(np.sum(2 * views[rows] - 3))
    return float(np.sqrt(err2 / dof)) if dof > 0 else math.nan


def trust_factors(displacement: np.ndarray, sigma: np.ndarray, shrink: float,
                  max_sigma: float = math.inf) -> np.ndarray:
    """How much of each triangulated point's displacement to keep: τ² / (τ² + κ σ²).

    The Wiener factor of a displacement δ = true + noise, the noise of variance κσ² (σ the
    point's standard deviation), the true displacement of prior variance τ², taken for the
    pose as the mean of ‖δ‖² over its points: a pose whose points move about as far as
    their noise lets them keeps little of it, and a point far noisier than the pose's
    displacement keeps almost none. (A prior per pose rather than ‖δ‖² per point: a noisy
    point that happens to move far is not trusted for it.) A point with σ above max_sigma
    (the reconstruction's `max_surface_distance`: it could be anywhere a point is
    accepted) is not trusted at all, and not counted in τ².

    Args:
        displacement: (k,3) δ = triangulated - inferred; sigma: (k,) their standard
            deviations (m); shrink: κ ≥ 0; max_sigma: the largest σ trusted (m).

    Returns:
        (k,) factors in [0,1]: 1 everywhere when κ is 0; 0 where σ is not finite or above
        max_sigma.
    """
    d2 = np.sum(np.asarray(displacement, dtype=np.float64) ** 2, axis=1)
    if not shrink:
        return np.ones(len(d2))
    sigma = np.asarray(sigma, dtype=np.float64)
    s2 = float(shrink) * sigma ** 2
    finite = np.isfinite(s2) & (sigma <= max_sigma)
    if not finite.any():
        return np.zeros(len(d2))
    tau2 = float(np.mean(d2[finite]))
    with np.errstate(invalid="ignore", divide="ignore"):
        f = tau2 / (tau2 + s2)
    return np.where(finite & np.isfinite(f), f, 0.0)


def fusion_factors(displacement: np.ndarray, sigma: np.ndarray | None, prior_sigma: np.ndarray, shrink: float,
                   gate: float | None = None, max_sigma: float = math.inf) -> tuple[np.ndarray, np.ndarray]:
    """How much of each triangulated point's displacement from the prior to keep:
    σ_p² / (σ_p² + κσ²), and 0 for an outlier ‖δ‖² > g² (σ_p² + κσ²).

    The prior (the corrected mesh) says the vertex is at X_p with standard deviation σ_p,
    the point says X_p + δ with standard deviation √κ σ (κ calibrates the point's σ, as in
    `trust_factors`); the fused position X_p + w δ weighs each by the other's variance.

    Args:
        displacement: (k,3) δ = triangulated - prior. sigma: (k,) the points' standard
            deviations (m), or None for exact texcoords (every point kept whole, no gate).
        prior_sigma: (k,) σ_p of the prior at those vertices (m).
        shrink: κ ≥ 0 (0: every point kept whole, no gate). gate: g (None: no gate).
        max_sigma: a point with σ above this is not trusted (as `trust_factors`).

    Returns:
        factors (k,) in [0,1] and outlier (k,) bool (the points the gate rejected).
    """
    d2 = np.sum(np.asarray(displacement, dtype=np.float64) ** 2, axis=1)
    if sigma is None or not shrink:
        return np.ones(len(d2)), np.zeros(len(d2), bool)
    sigma = np.asarray(sigma, dtype=np.float64)
    p2 = np.asarray(prior_sigma, dtype=np.float64) ** 2
    s2 = float(shrink) * sigma ** 2
    finite = np.isfinite(s2) & (sigma <= max_sigma)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        total = p2 + s2
        w = np.where(total > 0, p2 / total, 0.0)
        outlier = finite & (d2 > gate ** 2 * total) if gate is not None else np.zeros(len(d2), bool)
    return np.where(finite & ~outlier & np.isfinite(w), w, 0.0), outlier
