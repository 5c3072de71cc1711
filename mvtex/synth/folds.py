"""Folds made the way cloth makes them (DESIGN §8), on a chart of material coordinates.

A fold is a ridge in a 2-D chart of the material (meters of cloth along both axes). Along
its normal n the tangent angle follows phi(s) = -phi_max * exp(-s^2 / 2 w^2) *
sin(2 pi s / wavelength); integrating (cos phi, sin phi) gives a unit-speed cross-section,
so the fold keeps the material's lengths. Its in-plane part slides the material towards the
fold (`slide`, along n), its out-of-plane part is an offset along the surface normal
(`offset`, a ridge at the centre when phi_max > 0). The material on the +n side of the fold
stays where it is; the material on the -n side moves towards the fold by the length the fold
gathers (so a chart's +n side can be sewn to other pieces, and the -n side must end at a
free edge, a hem or a sleeve end). Along the ridge the fold fades out within `half_length`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_TABLE_S, _TABLE_AMP = 241, 17  # profile tables: samples along s, amplitude levels


_REACH = 3.0  # the profile is cut at +-3 widths along n (exp(-4.5) = 1 % of its peak angle)


def smoothstep(x: np.ndarray) -> np.ndarray:
    """3x^2 - 2x^3 on [0, 1], clamped outside."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def bump(r: np.ndarray) -> np.ndarray:
    """Smooth bump (1 - r^2)^2 on |r| < 1, 0 outside."""
    r2 = np.minimum(r * r, 1.0)
    return (1.0 - r2) ** 2


def mix(x) -> float:
    """Smooth periodic modulation in [0, 1]: how pose components vary a fold nonlinearly."""
    return 0.5 + 0.5 * np.sin(x)


def wrap(d: np.ndarray, period: float) -> np.ndarray:
    """Differences of a periodic coordinate wrapped into [-period/2, period/2)."""
    return np.mod(d + 0.5 * period, period) - 0.5 * period


@dataclass(frozen=True)
class Fold:
    """One fold in a chart (chart coordinates (p, q) in meters of material).

    Attributes:
        chart: which chart of the garment it lives on.
        p0, q0: its centre.
        beta: direction of its normal n = (cos beta, sin beta) in the chart.
        wavelength: of the angle profile along n (m).
        phi_max: peak tangent angle parameter (rad); > 0 puts a ridge at the centre.
        width: std of the Gaussian envelope along n, in wavelengths.
        half_length: reach of the compact envelope along the ridge (m).
    """

    chart: str
    p0: float
    q0: float
    beta: float
    wavelength: float
    phi_max: float
    width: float
    half_length: float

    @property
    def normal(self) -> np.ndarray:
        return np.array([np.cos(self.beta), np.sin(self.beta)])

    @property
    def reach(self) -> float:
        """How far along n the fold moves material on its fixed (+n) side (m)."""
        return _REACH * self.width * self.wavelength


def _cumulative(y: np.ndarray, dx: float) -> np.ndarray:
    """Trapezoid-rule integral of y along its last axis from its first sample."""
    out = np.zeros_like(y)
    np.cumsum(0.5 * dx * (y[..., 1:] + y[..., :-1]), axis=-1, out=out[..., 1:])
    return out


def _bilinear(table: np.ndarray, fi: np.ndarray, fj: np.ndarray) -> np.ndarray:
    """table (I, J) interpolated at fractional indices (fi, fj), clamped to the last cell."""
    i0 = np.clip(np.floor(fi).astype(int), 0, table.shape[0] - 2)
    j0 = np.clip(np.floor(fj).astype(int), 0, table.shape[1] - 2)
    ti, tj = fi - i0, fj - j0
    top = table[i0, j0] * (1 - tj) + table[i0, j0 + 1] * tj
    bottom = table[i0 + 1, j0] * (1 - tj) + table[i0 + 1, j0 + 1] * tj
    return top * (1 - ti) + bottom * ti


def fold_field(fold: Fold, dp: np.ndarray, dq: np.ndarray,
               fade=None) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Displacement field of one fold over material points at offsets (dp, dq) from its
    centre (each (m,) float64, already wrapped on a periodic chart).

    Args:
        fade: optional function of the ridge coordinate tau (s,) -> (s,) in [0, 1] that
            scales the angle (a fold fading out before a seam or an edge); constant along n,
            so every cross-section stays unit-speed.

    Returns:
        support: (s,) indices of the points the fold moves; slide: (s, 2) in-chart
        displacement; offset: (s,) displacement along the surface normal; peak: the
        largest tangent angle the fold reaches (rad).
    """
    n = fold.normal
    s = dp * n[0] + dq * n[1]
    tau = -dp * n[1] + dq * n[0]  # along the ridge
    width = fold.width * fold.wavelength
    support = np.flatnonzero((np.abs(tau) < fold.half_length) & (s < _REACH * width))
    s, tau = s[support], tau[support]
    amp = bump(tau / fold.half_length)
    if fade is not None:
        amp = amp * fade(tau)
    grid = np.linspace(-_REACH * width, _REACH * width, _TABLE_S)
    profile = np.exp(-0.5 * (grid / width) ** 2) * np.sin(2 * np.pi * grid / fold.wavelength)
    phi = -fold.phi_max * np.linspace(0.0, 1.0, _TABLE_AMP)[:, None] * profile
    slide = _cumulative(np.cos(phi) - 1.0, grid[1] - grid[0])
    slide -= slide[:, -1:]  # the +n side stays; the -n side slides towards the fold
    offset = _cumulative(np.sin(phi), grid[1] - grid[0])
    fi = amp * (_TABLE_AMP - 1)
    fj = np.clip((s - grid[0]) / (grid[1] - grid[0]), 0.0, _TABLE_S - 1.0)
    peak = abs(fold.phi_max) * float(amp.max(initial=0.0)) * float(np.abs(profile).max())
    return support, _bilinear(slide, fi, fj)[:, None] * n, _bilinear(offset, fi, fj), peak
