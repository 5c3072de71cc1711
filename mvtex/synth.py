"""The built-in datasets: a shirt-like garment with pose-driven folds (DESIGN §8), and a
flared skirt whose hem falls into flutes (`mvtex.skirt`), chosen by `SynthOptions.garment`.

The garment is a closed torso tube, open at collar and waist, in meters with y up and
its front facing +z. Its material is described by *material coordinates* (a, h): a is
the arc length around the rest cross-section (0 at the front centre, growing towards +x
there) and h the rest height. Because the rest tube is a cylinder, the (a, h) plane
unrolls onto it without distortion, and the two UV charts (front and back panel) are
just that plane scaled by one factor.

A ground-truth pose is built in two layers:

* a smooth *base* map (a, h) -> 3-D: the tube bent forward/back and sideways, twisted
  and with its shoulders lifted, like a rod whose cross-sections follow a rotating frame;
* *folds* made the way cloth makes them: along the fold normal s the tangent angle
  follows phi(s) = phi_max * env(s) * sin(2 pi s / wavelength), and integrating
  (cos phi, sin phi) gives a unit-speed profile, so edge lengths stay close to rest.
  Its in-plane part slides the material towards the fold, its out-of-plane part is an
  offset along the base surface's normal.

The *inferred* meshes come from a predictor fitted on the training poses (PCA of the
ground-truth shapes, of at most `MAX_BASIS_SHAPES` evenly spaced ones; ridge regression
from the pose to the PCA coefficients over all of them).
`synthesize` writes nothing; `mvtex.dataset.save_dataset` owns the file format, and
`write_synth` writes the same files while streaming the shapes to disk.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.integrate import cumulative_trapezoid
from scipy.special import expit, ndtr

from .dataset import default_split
from .mesh import edge_strain, edges, grid_faces

__all__ = [
    "GARMENTS",
    "MAX_BASIS_SHAPES",
    "POSE_DIM",
    "PosePredictor",
    "SynthOptions",
    "deform",
    "fit_predictor",
    "make_garment",
    "sample_poses",
    "synthesize",
    "write_synth",
]

SEMI_X = 0.18  # half width of the elliptical cross-section (x), m
SEMI_Z = 0.11  # half depth (z), m
HEIGHT = 0.64  # waist (y = -0.32) to collar (y = +0.32), m
N_AROUND = 64  # distinct vertex columns around the tube, 32 per panel
N_RINGS = 47  # rings from waist to collar: ~1.4 cm spacing both ways (square quads)
POSE_DIM = 12
_U0_FRONT, _U0_BACK, _CHART_WIDTH = 0.02, 0.52, 0.46  # chart placement in u
_TABLE_S, _TABLE_AMP = 241, 17  # fold profile tables: samples along s, amplitude levels
GARMENTS = ("shirt", "skirt")
_CHUNK = 256  # poses per block when streaming shapes to and from disk
MAX_BASIS_SHAPES = 1000  # most training shapes the predictor's PCA basis is computed from


@dataclass(frozen=True)
class SynthOptions:
    """Options of `synthesize`.

    Attributes:
        num_poses: number of poses K (at least 3, one per split).
        seed: seeds the poses and the 80/10/10 split.
        pca_components: PCA components of the predictor (its capacity).
        ridge: ridge penalty of the pose -> PCA-coefficient regression (bias unpenalized).
        garment: "shirt" (a torso tube with bend, twist and side folds) or "skirt" (a
            flared cone whose hem swings and falls into flutes, `mvtex.skirt`).
    """

    num_poses: int = 300
    seed: int = 0
    pca_components: int = 6
    ridge: float = 1e-2
    garment: str = "shirt"


# ----------------------------------------------------------------------------- garment


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


# ------------------------------------------------------------------------ deformation


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


# ------------------------------------------------------------------------- predictor


@dataclass(frozen=True)
class PosePredictor:
    """Linear pose -> shape predictor: ridge regression onto a PCA basis of the shapes.

    Attributes:
        mean: (3t,) float64 mean shape over t distinct vertex tracks.
        components: (k, 3t) float64 orthonormal PCA components.
        weights: (P + 1, k) float64 regression weights; the last row is the bias.
        expand: (n,) int64 vertex -> distinct track (vertices that coincide in every
            training shape, like seam copies, share a track and stay coincident).
    """

    mean: np.ndarray
    components: np.ndarray
    weights: np.ndarray
    expand: np.ndarray

    def predict(self, poses: np.ndarray) -> np.ndarray:
        """Predicted shapes of (K, P) poses, (K, n, 3) float32."""
        poses = np.atleast_2d(np.asarray(poses, dtype=np.float64))
        features = np.hstack([poses, np.ones((len(poses), 1))])
        flat = self.mean + (features @ self.weights) @ self.components
        return flat.reshape(len(poses), -1, 3)[:, self.expand].astype(np.float32)


def _basis_subset(num: int, cap: int) -> np.ndarray:
    """Indices of at most `cap` of `num` shapes, evenly spaced and sorted: all of them
    (0, 1, ..., num - 1) when num <= cap, else floor(i * num / cap) for i < cap."""
    count = min(num, cap)
    return np.arange(count, dtype=np.int64) * num // count


def fit_predictor(gt_train: np.ndarray, poses_train: np.ndarray, n_components: int = 6, ridge: float = 1e-2,
                  max_basis_shapes: int = MAX_BASIS_SHAPES) -> PosePredictor:
    """Fit PCA (few components) of the shapes and ridge regression from pose to coefficients.

    With few components and a model linear in the pose, the fit cannot follow folds
    whose position and depth depend nonlinearly on the pose: its meshes are smooth and
    off in tangential material position, like a learned cloth predictor's.

    Memory does not grow with the number of training shapes K. The PCA basis is computed
    from at most `max_basis_shapes` of them (evenly spaced in training order, so
    deterministic; all of them when K <= max_basis_shapes, and then the result is the
    plain PCA of all shapes) through their small Gram matrix. The mean shape and the ridge
    regression use ALL K shapes: they are read `_CHUNK` at a time, projected onto the
    basis, and only the (P + 1) x (P + 1) and (P + 1) x k normal equations are summed, so
    no (K, 3t) float64 array exists. A few components of shapes this smooth are pinned
    down by a thousand samples; the regression, whose error is what the inferred meshes
    show, still sees every pose.

    Args:
        gt_train: (K, n, 3) training shapes: an array, or anything with `.shape` that
            returns arrays for `gt_train[a:b]` and `gt_train[index_array]` (a memory map;
            it is read in blocks, never whole).
        poses_train: (K, P) their poses.
        n_components: PCA components kept (at most min(K, max_basis_shapes) - 1 are used).
        ridge: penalty on the pose weights (not on the bias).
        max_basis_shapes: most training shapes the PCA basis is computed from (>= 2).
    """
    gt = gt_train if hasattr(gt_train, "shape") and hasattr(gt_train, "__getitem__") else np.asarray(gt_train)
    poses = np.asarray(poses_train, dtype=np.float64)
    shape = tuple(gt.shape)
    if len(shape) != 3 or shape[2] != 3 or poses.ndim != 2 or len(poses) != shape[0] or shape[0] < 1:
        raise ValueError(f"expected gt_train (K, n, 3) and poses_train (K, P), got {shape} and {poses.shape}")
    if max_basis_shapes < 2:
        raise ValueError(f"max_basis_shapes must be at least 2, got {max_basis_shapes}")
    num = shape[0]
    blocks = [(lo, min(lo + _CHUNK, num)) for lo in range(0, num, _CHUNK)]
    # Tie vertices that coincide in every training shape; candidates come from the first.
    # Kept in the shapes' own (float32) type until the distinct tracks are gathered: every
    # step before that is a comparison or an ordering, exact in either type.
    _, first, expand = np.unique(np.asarray(gt[0:1])[0], axis=0, return_index=True, return_inverse=True)
    expand = expand.reshape(-1)
    differs = np.zeros(shape[1], bool)
    for lo, hi in blocks:
        block = np.asarray(gt[lo:hi])
        differs |= np.any(block[:, first[expand]] != block, axis=(0, 2))
    untied = np.flatnonzero(differs)
    first = np.concatenate([first, untied])
    expand[untied] = len(first) - len(untied) + np.arange(len(untied))

    def tracks(rows: np.ndarray) -> np.ndarray:
        """(r, 3t) float64 distinct tracks of (r, n, 3) shapes."""
        return rows[:, first].reshape(len(rows), -1).astype(np.float64)

    subset = _basis_subset(num, max_basis_shapes)
    everything = len(subset) == num
    centred = tracks(np.asarray(gt[0:num] if everything else gt[subset]))
    subset_mean = centred.mean(axis=0)
    centred -= subset_mean  # in place: the same values as centred - mean, one array fewer
    # PCA through the small (S, S) Gram matrix: S << 3t, much faster than an SVD of the data.
    eigval, eigvec = np.linalg.eigh(centred @ centred.T)
    keep = np.argsort(eigval)[::-1][: max(0, min(n_components, len(subset) - 1))]
    keep = keep[eigval[keep] > 1e-12 * max(eigval.max(), 1e-300)]
    components = (eigvec[:, keep].T @ centred) / np.sqrt(eigval[keep])[:, None]
    features = np.hstack([poses, np.ones((num, 1))])
    penalty = ridge * np.eye(features.shape[1])
    penalty[-1, -1] = 0.0
    if everything:  # one block: the centred shapes are all in memory already
        mean = subset_mean
        normal, rhs = features.T @ features, features.T @ (centred @ components.T)
    else:
        del centred
        mean = np.zeros_like(subset_mean)
        for lo, hi in blocks:
            mean += tracks(np.asarray(gt[lo:hi])).sum(axis=0)
        mean /= num
        normal, rhs = np.zeros((features.shape[1],) * 2), np.zeros((features.shape[1], len(keep)))
        for lo, hi in blocks:
            coeffs = (tracks(np.asarray(gt[lo:hi])) - mean) @ components.T
            normal += features[lo:hi].T @ features[lo:hi]
            rhs += features[lo:hi].T @ coeffs
    weights = np.linalg.solve(normal + penalty, rhs)
    return PosePredictor(mean, components, weights, expand)


# ------------------------------------------------------------------------- synthesize


def _garment_shape_function(garment: str):
    """((faces, uv, rest), shape) of a built-in garment, where shape(pose) -> (positions
    (n,3) in vertex order, fold info [(depth, wavelength, peak angle), ...])."""
    if garment == "shirt":
        faces, uv, rest = make_garment()
        a, h, inverse = _material_coords(rest, uv)

        def shape(pose):
            positions, info = _deform_material(a, h, pose)
            return positions[inverse], info

        return (faces, uv, rest), shape
    from . import skirt

    return skirt.make_garment(), skirt.deform_with_info


def _check_options(options: SynthOptions) -> None:
    if options.garment not in GARMENTS:
        raise ValueError(f"garment must be one of {', '.join(GARMENTS)}, got {options.garment!r}")
    if options.num_poses < 3:
        raise ValueError(f"num_poses must be at least 3 (one pose per split), got {options.num_poses}")
    if options.pca_components < 1 or options.ridge < 0:
        raise ValueError(f"need pca_components >= 1 and ridge >= 0, got {options.pca_components} and {options.ridge}")


class _Rows:
    """The rows `index` of a (K, n, 3) array or `_RowFile`, read only when indexed: the
    predictor fit reads the training shapes block by block through it."""

    def __init__(self, base, index: np.ndarray):
        self.base, self.index = base, index
        self.shape = (len(index), *base.shape[1:])

    def __getitem__(self, key) -> np.ndarray:
        return np.asarray(self.base[self.index[key]])


def _generate(options: SynthOptions, gt_out: np.ndarray, inferred_out: np.ndarray) -> tuple:
    """Fill gt_out and inferred_out ((K, n, 3) float32, in memory or `_RowFile`) pose by
    pose and block by block, and compute the statistics. The shapes are computed per pose
    (or per row of a block), so they do not depend on the block size; the statistics'
    means are sums of per-pose sums (equal to a one-pass mean up to rounding).

    Returns:
        (faces, uv, rest, poses, split, stats) as in `synthesize`.
    """
    (faces, uv, rest), shape = _garment_shape_function(options.garment)
    poses = sample_poses(options.num_poses, options.seed)
    depths, wavelengths, peaks = [], [], []
    for k, pose in enumerate(poses):
        positions, info = shape(pose)
        gt_out[k] = positions
        depths.append(max(d for d, _, _ in info))
        wavelengths += [w for d, w, _ in info if d >= 5e-3]
        peaks.append(max(p for _, _, p in info))
    split = default_split(options.num_poses, options.seed)
    train = np.asarray(split["train"], dtype=np.int64)
    predictor = fit_predictor(_Rows(gt_out, train), poses[train], options.pca_components, options.ridge)
    edge_list = edges(faces)
    # Per-pose sums (K,) float64: the means over poses and edges / vertices need no (K, e)
    # array, so memory does not grow with K.
    strain_gt = np.empty(options.num_poses)
    strain_inferred = np.empty(options.num_poses)
    squared = np.empty(options.num_poses)
    for lo in range(0, options.num_poses, _CHUNK):
        block = slice(lo, min(lo + _CHUNK, options.num_poses))
        inferred = predictor.predict(poses[block])
        inferred_out[block] = inferred
        gt = np.asarray(gt_out[block])
        strain_gt[block] = np.abs(edge_strain(gt, rest, edge_list)).sum(axis=1)
        strain_inferred[block] = np.abs(edge_strain(inferred, rest, edge_list)).sum(axis=1)
        squared[block] = np.sum((inferred.astype(np.float64) - gt.astype(np.float64)) ** 2, axis=(1, 2))

    def rmse(part: list[int]) -> float:
        # As `mesh.rms_distance` over the poses of one split.
        return float(np.sqrt(squared[part].sum() / (len(part) * len(rest))))

    stats = {
        "num_vertices": float(len(rest)),
        "num_faces": float(len(faces)),
        "pose_dim": float(POSE_DIM),
        "fold_depth_m": float(np.median(depths)),
        "fold_wavelength_m": float(np.median(wavelengths)) if wavelengths else 0.0,
        "max_fold_angle_deg": float(np.degrees(max(peaks))),
        "overhanging_pose_fraction": float(np.mean(np.array(peaks) > np.pi / 2)),
        "mean_abs_edge_strain_gt": float(strain_gt.sum() / strain_gt.size / len(edge_list)),
        "mean_abs_edge_strain_inferred": float(strain_inferred.sum() / strain_inferred.size / len(edge_list)),
        "rmse_inferred_train_m": rmse(split["train"]),
        "rmse_inferred_test_m": rmse(split["test"]),
    }
    return faces, uv, rest, poses, split, stats


def synthesize(options: SynthOptions = SynthOptions()) -> dict:
    """Generate the built-in dataset in memory (nothing is written).

    Returns:
        dict with name (the garment: "shirt" or "skirt"), faces (m, 3) int32, uv (n, 2) float32, rest (n, 3) float32,
        gt and inferred (K, n, 3) float32, poses (K, POSE_DIM) float32, split
        {"train", "val", "test": sorted lists of pose indices} (80/10/10, seeded), and
        stats, a dict of floats: num_vertices, num_faces, pose_dim; fold_depth_m (median
        over poses of the deepest fold's peak-to-trough normal offset); fold_wavelength_m
        (median over folds deeper than 5 mm); max_fold_angle_deg and
        overhanging_pose_fraction (poses whose steepest fold passes 90 degrees);
        mean_abs_edge_strain_gt / _inferred (mean |length / rest length - 1| over poses
        and edges); rmse_inferred_train_m / _test_m (per-vertex RMSE vs gt on that split).

    Raises:
        ValueError: num_poses < 3, pca_components < 1, ridge < 0 or an unknown garment.
    """
    _check_options(options)
    n = len(_garment_shape_function(options.garment)[0][2])
    gt = np.empty((options.num_poses, n, 3), dtype=np.float32)
    inferred = np.empty_like(gt)
    faces, uv, rest, poses, split, stats = _generate(options, gt, inferred)
    return dict(name=options.garment, faces=faces, uv=uv, rest=rest, gt=gt, inferred=inferred, poses=poses,
                split=split, stats=stats)


class _RowFile:
    """A (K, n, 3) float32 .npy file written and read in blocks of rows through short-lived
    memory maps: the process never keeps more than one block mapped, so its resident memory
    does not grow with K. Supports `obj[k] = rows`, `obj[block] = rows` and `obj[index]`."""

    def __init__(self, path, shape: tuple[int, ...]):
        from .io import create_npy

        self.path = path
        self.shape = shape
        create_npy(path, np.float32, shape)

    def _map(self, mode: str) -> np.memmap:
        return np.load(self.path, mmap_mode=mode, allow_pickle=False)

    def __setitem__(self, index, rows) -> None:
        mapped = self._map("r+")
        mapped[index] = rows
        mapped.flush()
        del mapped

    def __getitem__(self, index) -> np.ndarray:
        mapped = self._map("r")
        out = np.array(mapped[index])
        del mapped
        return out


def write_synth(path: str | os.PathLike, options: SynthOptions = SynthOptions()) -> dict:
    """Synthesize and save the dataset directory at `path` (format: DESIGN §4) atomically,
    streaming: the shapes go to gt.npy / inferred.npy block by block as they are made, so
    memory does not hold all poses, and the predictor fit reads the training shapes in
    blocks too (`fit_predictor`): peak memory does not grow with `num_poses`.
    The files are byte for byte those `mvtex.dataset.save_dataset` writes for
    `synthesize(options)` (tests/test_synth.py checks it).

    The statistics are also stored under "stats" in dataset.json, the garment under
    "garment".

    Returns:
        The `stats` dict of `synthesize`.
    """
    import json
    from pathlib import Path

    from .dataset import FORMAT, VERSION, validate_mesh
    from .io import atomic_path

    _check_options(options)
    path = Path(path)
    (faces, uv, rest), _ = _garment_shape_function(options.garment)
    validate_mesh(faces, uv, path)
    shape = (options.num_poses, len(rest), 3)
    with atomic_path(path) as tmp:
        tmp.mkdir()
        gt, inferred = _RowFile(tmp / "gt.npy", shape), _RowFile(tmp / "inferred.npy", shape)
        faces, uv, rest, poses, split, stats = _generate(options, gt, inferred)
        meta = {"format": FORMAT, "version": VERSION, "name": options.garment, "units": "m", "num_poses": shape[0],
                "num_vertices": shape[1], "pose_dim": int(poses.shape[1]), "garment": options.garment, "stats": stats}
        np.savez_compressed(tmp / "mesh.npz", faces=np.asarray(faces, np.int32), uv=np.asarray(uv, np.float32),
                            rest=np.asarray(rest, np.float32))
        np.save(tmp / "poses.npy", np.asarray(poses, np.float32), allow_pickle=False)
        (tmp / "split.json").write_text(json.dumps({k: [int(i) for i in split[k]] for k in ("train", "val", "test")}) + "\n")
        (tmp / "dataset.json").write_text(json.dumps(meta, indent=2) + "\n")
    return stats
