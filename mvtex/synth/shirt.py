"""The built-in shirt: a torso tube with pose-driven folds (DESIGN §8).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.integrate import cumulative_trapezoid
from scipy.special import expit, ndtr

from mvtex.data.mesh import grid_faces

SEMI_X = 0.18  # half width of the elliptical cross-section (x), m


SEMI_Z = 0.11  # half depth (z), m


HEIGHT = 0.64  # waist (y = -0.32) to collar (y = +0.32), m


N_AROUND = 64  # distinct vertex columns around the tube, 32 per panel


N_RINGS = 47  # rings from waist to collar: ~1.4 cm spacing both ways (square quads)


POSE_DIM = 12


_U0_FRONT, _U0_BACK, _CHART_WIDTH = 0.02, 0.52, 0.46  # chart placement in u


_TABLE_S, _TABLE_AMP = 241, 17  # fold profile tables: samples along s, amplitude levels


@lru_cache(maxsize=1)
def _ellipse_table() -> tuple[np.ndarray, np.ndarray]:
    """Angle theta and arc length from the front centre, for p = (A sin theta, B cos theta)."""
    theta = np.linspace(0.0, 2.0 * np.pi, 8193)
    speed = np.hypot(SEMI_X * np.cos(theta), SEMI_Z * np.sin(theta))
    return theta, cumulative_trapezoid(speed, theta, initial=0.0)


def _perimeter() -> float:
    return float(_ellipse_table()[1][-1])


@lru_cache(maxsize=1)
def _section_table() -> np.ndarray:
    """(4097, 2) cross-section points (x, z) at uniform arc-length steps (0.23 mm)."""
    theta, arc = _ellipse_table()
    t = np.interp(np.linspace(0.0, arc[-1], 4097), arc, theta)
    return np.stack([SEMI_X * np.sin(t), SEMI_Z * np.cos(t)], axis=1)


def _lerp(table: np.ndarray, start: float, step: float, x: np.ndarray) -> np.ndarray:
    """Rows of a table sampled at start + i * step, linearly interpolated at x (clamped).

    One gather replaces an np.interp (a binary search) per column: the base map is
    evaluated 3 x 300 times on 3,000 points and this is its inner loop.
    """
    f = (x - start) / step
    i = np.clip(np.floor(f).astype(np.intp), 0, len(table) - 2)
    t = np.clip(f - i, 0.0, 1.0)[:, None]
    return table[i] * (1.0 - t) + table[i + 1] * t


def _section(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rest cross-section point (x, z) at arc length a (any real; wraps around)."""
    table = _section_table()
    p = _perimeter()
    xz = _lerp(table, 0.0, p / (len(table) - 1), np.mod(a, p))
    return xz[:, 0], xz[:, 1]


def _wrap(d: np.ndarray) -> np.ndarray:
    """Arc-length difference wrapped into [-P/2, P/2)."""
    p = _perimeter()
    return np.mod(d + 0.5 * p, p) - 0.5 * p


def _uv_scale() -> float:
    """UV units per meter of material, the same along u and v (no texture distortion)."""
    return _CHART_WIDTH / (0.5 * _perimeter())


@lru_cache(maxsize=1)
def _garment() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    half = N_AROUND // 2
    step = _perimeter() / N_AROUND
    # Positions are computed once per distinct column, so the two copies of a seam
    # vertex share them bit for bit.
    sx, sz = _section(-0.25 * _perimeter() + step * np.arange(N_AROUND))
    heights = np.linspace(-0.5 * HEIGHT, 0.5 * HEIGHT, N_RINGS)
    j = np.arange(half + 1)
    ring = np.repeat(np.arange(N_RINGS), half + 1)
    col = np.tile(j, N_RINGS)
    # Front chart: left seam (x<0) -> right seam; back chart: right seam -> left seam,
    # so u runs left to right on each panel seen from its own outside.
    distinct = np.concatenate([col, (half + col) % N_AROUND])
    u = np.concatenate([_U0_FRONT + col * (_CHART_WIDTH / half), _U0_BACK + col * (_CHART_WIDTH / half)])
    ring2 = np.concatenate([ring, ring])
    uv = np.stack([u, 0.5 + _uv_scale() * heights[ring2]], axis=1)
    rest = np.stack([sx[distinct], heights[ring2], sz[distinct]], axis=1)

    # Both splits of a quad are counter-clockwise seen from outside: d/da x d/dh points outward.
    return grid_faces(N_RINGS, half, charts=2), uv.astype(np.float32), rest.astype(np.float32)


def make_garment() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rest garment.

    Returns:
        faces: (m, 3) int32, counter-clockwise seen from outside (m = 5888).
        uv: (n, 2) float32 in [0, 1]^2; front chart u in [0.02, 0.48], back chart
            u in [0.52, 0.98], v in about [0.18, 0.82] (n = 3102).
        rest: (n, 3) float32 rest positions in meters, bounding box centred at the origin.
    """
    faces, uv, rest = _garment()
    return faces.copy(), uv.copy(), rest.copy()


def sample_poses(num_poses: int, seed: int) -> np.ndarray:
    """Pose vectors, uniform in [-1, 1].

    Components: 0 forward(+)/back bend, 1 side bend (+ leans towards -x), 2 twist,
    3 and 4 left/right shoulder lift, 5..11 modulate fold position, direction, depth
    and wavelength (nonlinearly).

    Returns:
        (num_poses, POSE_DIM) float32.
    """
    rng = np.random.default_rng(seed)
    return rng.uniform(-1.0, 1.0, size=(num_poses, POSE_DIM)).astype(np.float32)


class _BaseMap:
    """Smooth torso deformation (a, h) -> 3-D for one pose.

    A rod model: the centreline is integrated from a frame R(h) = Rx(bend) Rz(side) Ry(twist)
    whose angles vary smoothly with height, and each cross-section rides its frame.
    Lengths along the centreline are kept; off-axis fibres strain by curvature x offset.
    """

    def __init__(self, pose: np.ndarray):
        g = np.linspace(-0.5 * HEIGHT - 0.16, 0.5 * HEIGHT + 0.16, 321)  # 0 at [160]
        self.grid = (g[0], g[1] - g[0])
        p = pose
        # Bends have a Gaussian curvature profile around a pose-dependent height and the
        # frame at h = 0 is held fixed, which keeps the garment centred. The products and
        # the moving bend height make the shapes nonlinear in the pose, as a body's are.
        bend = 0.24 * p[0] + 0.05 * p[0] ** 2
        bend_at = -0.06 + 0.06 * np.sin(np.pi * (p[5] + 0.3 * p[0]))
        side_at = -0.02 + 0.05 * np.cos(np.pi * p[7])
        ax = bend * (ndtr((g - bend_at) / 0.2) - ndtr(-bend_at / 0.2))
        az = 0.16 * p[1] * (ndtr((g - side_at) / 0.2) - ndtr(-side_at / 0.2))
        tw = (0.35 * p[2] + 0.08 * p[0] * p[1]) * g / HEIGHT
        axis_y = np.stack([-np.sin(az), np.cos(az) * np.cos(ax), np.cos(az) * np.sin(ax)], 1)
        centre = cumulative_trapezoid(axis_y, g, axis=0, initial=0.0)
        # Everything that depends on h alone, tabulated: frame angles' cos/sin, centreline.
        self.table = np.column_stack([np.cos(tw), np.sin(tw), np.cos(az), np.sin(az), np.cos(ax), np.sin(ax),
                                      centre - centre[160]])
        self.lift = 0.012 * (0.5 + 0.5 * pose[3:5])  # left (x<0), right shoulder, m
        # The garment rides on the body: its material shifts around and up/down the torso.
        # That is isometric, changes little of the shape and much of where material is,
        # and a predictor linear in the pose cannot follow it.
        self.ride = (0.012 * np.sin(np.pi * p[9] + 0.5 * p[2]), 0.006 * np.cos(np.pi * p[11]))

    def __call__(self, a: np.ndarray, h: np.ndarray) -> np.ndarray:
        a, h = a + self.ride[0], h + self.ride[1]  # material -> body coordinates
        x, z = _section(a)
        q = _perimeter() / 4
        ramp = _smoothstep((h + 0.05) / 0.37)
        y = ramp * (self.lift[0] * _bump(_wrap(a + q) / 0.25) + self.lift[1] * _bump(_wrap(a - q) / 0.25))
        cos_tw, sin_tw, cos_az, sin_az, cos_ax, sin_ax, cx, cy, cz = _lerp(self.table, *self.grid, h).T
        x, z = x * cos_tw + z * sin_tw, z * cos_tw - x * sin_tw
        x, y = x * cos_az - y * sin_az, x * sin_az + y * cos_az
        y, z = y * cos_ax - z * sin_ax, y * sin_ax + z * cos_ax
        return np.stack([x + cx, y + cy, z + cz], axis=1)

    def with_normal(self, a: np.ndarray, h: np.ndarray, eps: float = 1e-5) -> tuple[np.ndarray, np.ndarray]:
        """Positions (m, 3) and unit outward normals d/da x d/dh (forward differences)."""
        m = a.size
        x = self(np.concatenate([a, a + eps, a]), np.concatenate([h, h, h + eps]))
        n = np.cross(x[m : 2 * m] - x[:m], x[2 * m :] - x[:m])
        return x[:m], n / np.linalg.norm(n, axis=1, keepdims=True)


@dataclass(frozen=True)
class _Fold:
    a0: float  # centre, material coordinates (m)
    h0: float
    beta: float  # direction of the fold normal n = (cos beta, sin beta) in the (a, h) plane
    wavelength: float
    phi_max: float  # peak tangent angle (rad); its sign picks trough or ridge at the centre
    width: float  # std of the Gaussian envelope along n, in wavelengths
    half_length: float  # compact envelope along the ridge


def _bump(r: np.ndarray) -> np.ndarray:
    """Smooth bump (1 - r^2)^2 on |r| < 1, 0 outside."""
    r2 = np.minimum(r * r, 1.0)
    return (1.0 - r2) ** 2


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _mix(x: float) -> float:
    """Smooth periodic modulation in [0, 1]: how pose components vary a fold nonlinearly."""
    return 0.5 + 0.5 * np.sin(x)


def _folds(p: np.ndarray) -> list[_Fold]:
    """Fold templates of a pose; each is gated by its driver (bend, twist, lift)."""
    q = _perimeter() / 4
    pi = np.pi
    mix = _mix
    twist_dir = np.tanh(3.0 * p[2])  # smooth flip of the diagonal with the twist's sign
    # Gates rise smoothly from exactly 0, so a fold is absent (and costs nothing) until its
    # driver passes a threshold.
    forward, backward = _smoothstep((p[0] + 0.1) / 0.6), _smoothstep((0.1 - p[0]) / 0.6)
    left, right = _smoothstep(p[1] / 0.6), _smoothstep(-p[1] / 0.6)
    twist = _smoothstep((abs(p[2]) - 0.05) / 0.5)
    # A panel holds one large fold system at a time: where a bend compresses a panel its
    # twist folds give way, since two steep folds crossing cannot both keep lengths.
    front_twist, back_twist = twist * (1 - forward), twist * (1 - backward)
    return [
        # Horizontal compression folds on the front when bending forward; tilted by side bend.
        _Fold(0.05 * np.sin(pi * p[7]) - 0.04 * p[1], -0.04 + 0.045 * np.cos(pi * p[6] + 0.5 * p[0]),
              pi / 2 + 0.25 * p[1] + 0.12 * np.sin(pi * p[8]), 0.06 + 0.02 * mix(pi * p[8] + p[5]),
              forward * (1.2 + 0.85 * mix(pi * p[5] + 0.7 * p[6])), 0.6, 0.2),
        # The same on the back when bending backward.
        _Fold(2 * q + 0.05 * np.sin(pi * p[10]), -0.02 + 0.05 * np.sin(pi * p[5] - p[6]),
              pi / 2 - 0.2 * p[1] + 0.1 * np.cos(pi * p[11]), 0.065 + 0.02 * mix(pi * p[7] + p[8]),
              -backward * (0.9 + 0.75 * mix(pi * p[9])), 0.5, 0.2),
        # Diagonal twist folds, front and back, along the direction the twist compresses.
        _Fold(0.06 * p[10] + 0.03 * np.sin(pi * p[7]), -0.03 + 0.03 * np.sin(pi * p[9]),
              pi / 2 + 0.45 * twist_dir + 0.06 * p[9], 0.06 + 0.025 * expit(3 * p[10] - p[11]),
              front_twist * (0.8 + 0.8 * mix(pi * p[11] + 2 * p[2])), 0.5, 0.2),
        _Fold(2 * q + 0.06 * np.sin(pi * p[11]), -0.03 * np.cos(pi * p[8]),
              pi / 2 + 0.42 * twist_dir - 0.06 * p[8], 0.065 + 0.02 * mix(pi * p[6] - p[2]),
              -back_twist * (0.7 + 0.5 * mix(pi * p[5] * p[9])), 0.5, 0.18),
        # Side folds on the side a side bend compresses, across the side seams.
        _Fold(-q - 0.02 + 0.03 * p[11], 0.02 + 0.05 * np.sin(pi * p[10] + p[1]),
              pi / 2 + 0.2 * np.sin(pi * p[5]), 0.05 + 0.015 * mix(pi * p[9]),
              left * (0.85 + 0.45 * mix(pi * p[8] - p[9])), 0.5, 0.12),
        _Fold(q + 0.02 - 0.03 * p[10], 0.01 + 0.05 * np.cos(pi * p[11] - p[1]),
              pi / 2 - 0.2 * np.sin(pi * p[6]), 0.05 + 0.015 * mix(pi * p[7] * p[8]),
              -right * (0.85 + 0.45 * mix(pi * p[11])), 0.5, 0.12),
        # Drape folds below a lifted shoulder, on the front.
        _Fold(-q / 2, 0.13 + 0.02 * p[6], pi / 2 - 0.45 + 0.1 * p[7], 0.05 + 0.015 * expit(2 * p[11]),
              _smoothstep((p[3] + 0.1) / 0.7) * (0.7 + 0.5 * mix(pi * p[10] + p[3])), 0.5, 0.12),
        _Fold(q / 2, 0.13 - 0.02 * p[5], pi / 2 + 0.45 - 0.1 * p[7], 0.05 + 0.015 * expit(-2 * p[9]),
              _smoothstep((p[4] + 0.1) / 0.7) * (0.7 + 0.5 * mix(pi * p[9] - p[4])), 0.5, 0.12),
    ]


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


def _fold_field(fold: _Fold, a: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Displacement field of one fold over material points (a, h), each (m,) float64.

    Returns:
        support: (s,) indices of the points the fold moves; slide: (s, 2) in-plane
        displacement in (a, h); offset: (s,) displacement along the surface normal;
        peak: the largest tangent angle the fold reaches (rad).
    """
    n = np.array([np.cos(fold.beta), np.sin(fold.beta)])
    da, dh = _wrap(a - fold.a0), h - fold.h0
    s = da * n[0] + dh * n[1]
    tau = -da * n[1] + dh * n[0]  # along the ridge
    support = np.flatnonzero(np.abs(tau) < fold.half_length)
    s, tau = s[support], tau[support]
    # The envelope along the ridge has compact support (so a fold never reaches around
    # the tube to meet itself) and fades towards collar and waist.
    amp = _bump(tau / fold.half_length) * _smoothstep((0.5 * HEIGHT - 0.03 - np.abs(fold.h0 + tau * n[0])) / 0.08)
    # The envelope along the ridge scales phi, not the result, so every cross-section is
    # unit-speed; tabulate the integrals over (amplitude level, s) once per fold.
    width = fold.width * fold.wavelength
    grid = np.linspace(-4 * width, 4 * width, _TABLE_S)
    profile = np.exp(-0.5 * (grid / width) ** 2) * np.sin(2 * np.pi * grid / fold.wavelength)
    phi = fold.phi_max * np.linspace(0.0, 1.0, _TABLE_AMP)[:, None] * profile
    slide = _cumulative(np.cos(phi) - 1.0, grid[1] - grid[0])
    slide -= slide[:, _TABLE_S // 2 : _TABLE_S // 2 + 1]  # both sides slide towards the fold
    offset = _cumulative(np.sin(phi), grid[1] - grid[0])  # phi is odd: 0 at both ends
    fi = amp * (_TABLE_AMP - 1)
    fj = np.clip((s - grid[0]) / (grid[1] - grid[0]), 0.0, _TABLE_S - 1.0)
    peak = abs(fold.phi_max) * float(amp.max(initial=0.0)) * float(np.abs(profile).max())
    return support, _bilinear(slide, fi, fj)[:, None] * n, _bilinear(offset, fi, fj), peak


def _deform_material(a: np.ndarray, h: np.ndarray, pose: np.ndarray) -> tuple[np.ndarray, list[tuple]]:
    """Ground-truth positions (m, 3) float64 of material points (a, h) (each (m,)), and
    per fold a tuple (depth = peak-to-trough normal offset in m, wavelength, peak angle)."""
    pose = np.asarray(pose, dtype=np.float64)
    slide = np.zeros((a.size, 2))
    offset = np.zeros(a.size)
    info = []
    for fold in _folds(pose):
        if fold.phi_max == 0.0:  # gated off
            info.append((0.0, fold.wavelength, 0.0))
            continue
        support, fold_slide, fold_offset, peak = _fold_field(fold, a, h)
        slide[support] += fold_slide
        offset[support] += fold_offset
        info.append((float(np.ptp(fold_offset)), fold.wavelength, peak))
    positions, normals = _BaseMap(pose).with_normal(a + slide[:, 0], h + slide[:, 1])
    return positions + offset[:, None] * normals, info


def _material_coords(rest: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(a, h) of the distinct rest positions and the vertex -> distinct index."""
    _, first, inverse = np.unique(np.asarray(rest), axis=0, return_index=True, return_inverse=True)
    u = np.asarray(uv, dtype=np.float64)[first, 0]
    q = _perimeter() / 4
    a = np.where(u >= 0.5, (u - _U0_BACK) / _uv_scale() + q, (u - _U0_FRONT) / _uv_scale() - q)
    return a, np.asarray(rest, dtype=np.float64)[first, 1], inverse.reshape(-1)


def deform(rest: np.ndarray, uv: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """The ground-truth mesh of one pose.

    Args:
        rest: (n, 3) rest positions and uv: (n, 2) texture coordinates, from `make_garment`
            (the material coordinates are read from them).
        pose: (POSE_DIM,) pose vector in [-1, 1].

    Returns:
        (n, 3) float32 positions; vertices with equal rest positions (seam copies) get
        identical positions.
    """
    a, h, inverse = _material_coords(rest, uv)
    return _deform_material(a, h, pose)[0][inverse].astype(np.float32)
