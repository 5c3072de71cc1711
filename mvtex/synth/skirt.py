"""The second built-in garment: a flared skirt whose hem falls into flutes (DESIGN §8).

The skirt is a truncated cone in meters, y up, waist at the top (radius 0.15 m) and hem
at the bottom (radius 0.30 m), its front facing +z. A cone is developable: its material is
the flat annular sector it unrolls to, and the two UV charts (front and back panel, each
half of the sector) are that flat material scaled by one factor, so uv is undistorted.
Material coordinates are (theta, s): the angle around the axis (0 at the front centre,
growing towards +x there) and the slant distance down from the waist.

A ground-truth pose is built per horizontal ring of material, the way a skirt's hem
drapes:

* *flutes*: radial folds that start below the hips and deepen towards the hem. Along a
  ring the tangent turns by the circle's own turning plus a fold angle
  phi = phi_max * env(s) * exp(-sigma^2 / 2 w^2) sin(2 pi sigma) (sigma: angle from the
  flute's centre in wavelengths). Integrating the unit tangent gives a curve of exactly
  the ring's material length (no stretch around the ring) that gathers the excess cloth
  into the flutes; past 90 degrees a flute overhangs. A flute's wavelength is an angle,
  so it widens towards the hem, as real flutes do;
* a smooth base motion: the hem swings forward/back and sideways behind the waist (the
  rings drop less where they swing, which keeps the slant fibres' length), the cloth
  rotates around the body (more at the hem: a twist), and the hips tilt.

Flute positions, depths and wavelengths depend nonlinearly on the pose (the swing
direction gathers the cloth on the opposite side). The inferred meshes come from the
same fitted predictor as the shirt's (`mvtex.synth.predictor.fit_predictor`).

The skirt is worn: its body (`make_body`, `pose_body`) is the lower half of a mannequin,
the waist, hips and upper legs as one smooth closed surface, posed by the same pose
vector: the legs swing with the hem (turning about the hip joints so that they stay where
the hem's centre goes) and the hips tilt as the skirt's waist does.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.special import expit

from mvtex.data.mesh import grid_faces
from mvtex.synth.folds import smoothstep
from mvtex.synth.mannequin import elliptic_stack, mesh_implicit, round_cone, smooth_min

WAIST_RADIUS = 0.15  # m


HEM_RADIUS = 0.30  # m


SLANT = 0.56  # waist to hem along the cone, m


SIN_A = (HEM_RADIUS - WAIST_RADIUS) / SLANT  # sine of the cone's half angle


COS_A = float(np.sqrt(1.0 - SIN_A**2))


HEIGHT = SLANT * COS_A  # about 0.54 m, waist at +HEIGHT/2, hem at -HEIGHT/2


N_AROUND = 128  # distinct vertex columns around the skirt, 64 per panel


N_RINGS = 24  # rings from hem to waist, 2.4 cm apart along the slant


SUB = 8  # ring samples per column when integrating a ring's curve


POSE_DIM = 12


N_FLUTES = 8


_FLUTE_WIDTH = 0.5  # Gaussian envelope of a flute's angle profile, in wavelengths


_U_SCALE = 0.755  # uv units per meter of material (both charts fit [0, 1]^2 stacked)


_V0_FRONT, _V0_BACK = 0.52, 0.02


def _ring_slant() -> np.ndarray:
    """(N_RINGS,) slant distance from the waist of each ring, ring 0 at the hem."""
    return SLANT * (1.0 - np.arange(N_RINGS) / (N_RINGS - 1))


def _column_theta() -> np.ndarray:
    """(N_AROUND,) angle of each distinct column, from the left side seam (x < 0) onwards."""
    return -0.5 * np.pi + 2.0 * np.pi * np.arange(N_AROUND) / N_AROUND


@lru_cache(maxsize=1)
def _garment() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    half = N_AROUND // 2
    s = _ring_slant()
    radius = WAIST_RADIUS + s * SIN_A
    y = 0.5 * HEIGHT - s * COS_A
    theta = _column_theta()
    j = np.arange(half + 1)
    ring = np.repeat(np.arange(N_RINGS), half + 1)
    col = np.tile(j, N_RINGS)
    # Front chart: left seam -> right seam; back chart: right seam -> left seam, so u runs
    # left to right on each panel seen from its own outside. Seam copies name one column.
    distinct = np.concatenate([col, (half + col) % N_AROUND])
    ring2 = np.concatenate([ring, ring])
    rest = np.stack([radius[ring2] * np.sin(theta[distinct]), y[ring2], radius[ring2] * np.cos(theta[distinct])], 1)
    # Unrolled cone: a ring at slant s is an arc of radius rho = s + WAIST_RADIUS / SIN_A
    # around the apex, and the angle theta from the panel's centre becomes theta * SIN_A.
    local = np.concatenate([-0.5 * np.pi + j[col] * np.pi / half] * 2)
    rho = s[ring2] + WAIST_RADIUS / SIN_A
    omega = local * SIN_A
    outer = SLANT + WAIST_RADIUS / SIN_A
    v0 = np.where(np.arange(len(distinct)) < len(col), _V0_FRONT, _V0_BACK)
    uv = np.stack([0.5 + _U_SCALE * rho * np.sin(omega), v0 + _U_SCALE * (outer - rho * np.cos(omega))], axis=1)
    # Both splits of a quad are counter-clockwise seen from outside (d/dtheta x d/dh points out).
    faces = grid_faces(N_RINGS, half, charts=2)
    index = ring2 * N_AROUND + distinct  # vertex -> distinct (ring, column) point
    return faces, uv.astype(np.float32), rest.astype(np.float32), index


def make_garment() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rest skirt.

    Returns:
        faces: (m, 3) int32, counter-clockwise seen from outside (m = 5600).
        uv: (n, 2) float32; front chart v in [0.52, 0.98], back chart v in [0.02, 0.48],
            each an undistorted copy of its unrolled panel (n = 2958).
        rest: (n, 3) float32 rest positions in meters, bounding box centred at the origin.
    """
    faces, uv, rest, _ = _garment()
    return faces.copy(), uv.copy(), rest.copy()


def _mix(x):
    return 0.5 + 0.5 * np.sin(x)


@dataclass(frozen=True)
class _Flute:
    theta: float  # centre angle on the body (rad)
    wavelength: float  # angular wavelength (rad)
    phi_max: float  # peak fold angle parameter (rad), sign: ridge or trough at the centre
    start: float  # slant distance where the flute begins (m)


def _tilt(pose: np.ndarray) -> np.ndarray:
    """The hips' tilt: a rotation about x then z (3,3), about the waist's centre."""
    ax, az = 0.06 * pose[3], 0.05 * pose[4]
    rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    rz = np.array([[np.cos(az), -np.sin(az), 0], [np.sin(az), np.cos(az), 0], [0, 0, 1]])
    return rz @ rx


def _base(pose: np.ndarray) -> dict:
    p = pose
    swing = np.array([0.06 * p[1], 0.075 * p[0] + 0.015 * p[0] ** 2])  # hem offset (x, z), m
    # The cloth rotates around the body: by an amount the pose controls nonlinearly, and
    # more at the hem than at the waist.
    ride = 0.07 * np.sin(np.pi * p[9] + 0.5 * p[2])
    twist = 0.22 * p[2] + 0.05 * p[0] * p[1]
    return dict(swing=swing, ride=ride, twist=twist)


def _flutes(pose: np.ndarray) -> list[_Flute]:
    """Flute templates of a pose: cloth gathers opposite the swing, where the hem is slack."""
    p = pose
    swing = _base(pose)["swing"]
    direction = swing / 0.09  # about unit at full swing
    out = []
    for k in range(N_FLUTES):
        a = 5 + k % 7  # the fold-modulating components
        b = 5 + (k + 3) % 7
        theta = 2.0 * np.pi * k / N_FLUTES + 0.22 * np.sin(np.pi * p[a] + k)
        facing = np.array([np.sin(theta), np.cos(theta)]) @ direction
        slack = 0.5 - 0.55 * facing + 0.25 * np.sin(np.pi * p[b] + 0.7 * p[a])
        amplitude = 2.0 * smoothstep(slack) * (0.7 + 0.3 * _mix(np.pi * p[a] * p[b] + k))
        out.append(_Flute(theta=theta, wavelength=0.19 + 0.08 * expit(2.5 * p[b] - p[a]),
                          phi_max=(1.0 if k % 2 == 0 else -1.0) * amplitude,
                          start=0.08 + 0.12 * _mix(np.pi * p[(k + 5) % 7 + 5] + 0.5 * k)))
    return out


def _profile(sigma: np.ndarray) -> np.ndarray:
    return np.exp(-0.5 * (sigma / _FLUTE_WIDTH) ** 2) * np.sin(2.0 * np.pi * sigma)


@lru_cache(maxsize=1)
def _profile_peak() -> float:
    return float(np.abs(_profile(np.linspace(-2.0, 2.0, 4001))).max())


def _flute_depth(flute: _Flute) -> float:
    """Peak-to-trough normal offset of a flute at the hem (m), from its profile integral."""
    sigma = np.linspace(-4 * _FLUTE_WIDTH, 4 * _FLUTE_WIDTH, 801)
    offset = np.cumsum(np.sin(flute.phi_max * _profile(sigma))) * (sigma[1] - sigma[0])
    return float(HEM_RADIUS * flute.wavelength * np.ptp(offset))


def _cumtrapz(y: np.ndarray, dx: float) -> np.ndarray:
    out = np.zeros_like(y)
    np.cumsum(0.5 * dx * (y[..., 1:] + y[..., :-1]), axis=-1, out=out[..., 1:])
    return out


def deform_with_info(pose: np.ndarray) -> tuple[np.ndarray, list[tuple[float, float, float]]]:
    """Ground-truth positions of one pose and its flute statistics.

    Returns:
        (n, 3) float64 positions in `make_garment`'s vertex order (seam copies identical);
        per flute (depth at the hem in m, wavelength at the hem in m, peak fold angle in rad).
    """
    pose = np.asarray(pose, dtype=np.float64)
    s = _ring_slant()
    radius = WAIST_RADIUS + s * SIN_A
    base = _base(pose)
    frac = s / SLANT
    rotation = base["ride"] + base["twist"] * frac**2  # per ring
    # Each ring is integrated over its material angle, in body angle terms: the flutes sit
    # at fixed body angles, so in material angle at (body angle - the ring's rotation).
    M = N_AROUND * SUB
    theta = -0.5 * np.pi + 2.0 * np.pi * np.arange(M + 1) / M
    dtheta = 2.0 * np.pi / M
    phi = np.zeros((N_RINGS, M + 1))
    info = []
    for flute in _flutes(pose):
        centre = flute.theta - rotation[:, None]
        sigma = (np.mod(theta[None] - centre + np.pi, 2.0 * np.pi) - np.pi) / flute.wavelength
        env = smoothstep((s - flute.start) / (SLANT - flute.start))
        phi += flute.phi_max * env[:, None] * _profile(sigma)
        info.append((_flute_depth(flute), HEM_RADIUS * flute.wavelength, abs(flute.phi_max) * _profile_peak()))
    # Tangent angle: the circle's turning spread over the length the flutes leave, plus phi.
    progress = _cumtrapz(np.cos(phi), dtheta)
    psi = -0.5 * np.pi + 2.0 * np.pi * progress / progress[:, -1:] + phi
    curve = radius[:, None, None] * np.stack([_cumtrapz(np.cos(psi), dtheta), -_cumtrapz(np.sin(psi), dtheta)], -1)
    gap = curve[:, -1] - curve[:, 0]
    curve -= gap[:, None, :] * ((theta - theta[0]) / (2.0 * np.pi))[None, :, None]
    curve -= curve[:, :M].mean(axis=1, keepdims=True)
    xz = curve[:, : M : SUB]  # (N_RINGS, N_AROUND, 2) at the columns
    cos_r, sin_r = np.cos(rotation)[:, None], np.sin(rotation)[:, None]
    x = xz[..., 0] * cos_r + xz[..., 1] * sin_r
    z = -xz[..., 0] * sin_r + xz[..., 1] * cos_r
    # The hem swings behind the waist (offset ~ frac^2); each ring drops by what is left of
    # the slant fibre's vertical extent, so the fibres keep their length.
    offset = base["swing"][None] * frac[:, None] ** 2
    slope = np.linalg.norm(2.0 * base["swing"] * frac[:, None] / SLANT, axis=1)
    drop = np.sqrt(np.maximum(COS_A**2 - slope**2, 0.25))
    ds = SLANT / (N_RINGS - 1)
    y = 0.5 * HEIGHT - np.concatenate([np.cumsum((0.5 * ds * (drop[1:] + drop[:-1]))[::-1])[::-1], [0.0]])
    points = np.stack([x + offset[:, 0:1], np.broadcast_to(y[:, None], x.shape), z + offset[:, 1:2]], -1)
    # Hips tilt: a small rotation about x then z around the waist centre.
    waist = np.array([0.0, 0.5 * HEIGHT, 0.0])
    points = (points.reshape(-1, 3) - waist) @ _tilt(pose).T + waist
    return points[_garment()[3]], info


def sample_poses(num_poses: int, seed: int) -> np.ndarray:
    """Pose vectors, uniform in [-1, 1]: (num_poses, POSE_DIM) float32 (components: `deform`)."""
    rng = np.random.default_rng(seed)
    return rng.uniform(-1.0, 1.0, size=(num_poses, POSE_DIM)).astype(np.float32)


def deform(pose: np.ndarray) -> np.ndarray:
    """The ground-truth skirt of one pose, (n, 3) float32 in `make_garment`'s vertex order;
    seam copies get identical positions.

    Pose components (each in [-1, 1]): 0 hem swing forward(+)/back, 1 sideways (+x),
    2 twist, 3 and 4 hip tilt about x and z, 5..11 modulate the flutes' positions, depths,
    wavelengths and starts and (9) how far the cloth rotates around the body.
    """
    return deform_with_info(pose)[0].astype(np.float32)


# -- the body: waist, hips and upper legs --------------------------------------------------------

_HIPS_PROFILE = np.array([  # y, semi-axis x, semi-axis z (m): from below the hips to above the waist
    [-0.06, 0.150, 0.115], [0.04, 0.168, 0.128], [0.12, 0.160, 0.125], [0.20, 0.142, 0.118],
    [0.27, 0.136, 0.118], [0.34, 0.140, 0.112], [0.41, 0.145, 0.105]])


HIP_HEIGHT = 0.02  # the legs turn about (0, HIP_HEIGHT, 0)


_KNEE_HEIGHT = -0.37


def body_implicit(points: np.ndarray) -> np.ndarray:
    """(n,) implicit function of the skirt's body at rest (negative inside)."""
    d = elliptic_stack(points, _HIPS_PROFILE, 0.07)
    for side in (1.0, -1.0):
        d = smooth_min(d, round_cone(points, (side * 0.085, HIP_HEIGHT, 0.0), (side * 0.09, _KNEE_HEIGHT, 0.01),
                                     0.083, 0.056), 0.05)
    return d


@lru_cache(maxsize=1)
def _body() -> tuple[np.ndarray, np.ndarray]:
    return mesh_implicit(body_implicit, (-0.3, -0.5, -0.2), (0.3, 0.47, 0.2), 0.024)


def make_body() -> tuple[np.ndarray, np.ndarray]:
    """The skirt's body at rest: faces (mb,3) int32 (outward) and vertices (nb,3) float32."""
    vertices, faces = _body()
    return faces.copy(), vertices.astype(np.float32)


def _leg_swing(pose: np.ndarray) -> np.ndarray:
    """The legs' turn (3,3) about (0, HIP_HEIGHT, 0): the point of the legs at the hem's
    height goes where the skirt's hem centre goes."""
    swing = _base(pose)["swing"]
    drop = HIP_HEIGHT + 0.5 * HEIGHT
    ax, az = -np.arctan2(swing[1], drop), np.arctan2(swing[0], drop)
    rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    rz = np.array([[np.cos(az), -np.sin(az), 0], [np.sin(az), np.cos(az), 0], [0, 0, 1]])
    return rz @ rx


def pose_body(pose: np.ndarray) -> np.ndarray:
    """The skirt's body in one pose, (nb,3) float32 in `make_body`'s vertex order."""
    return _posed_body(pose).astype(np.float32)


def _posed_body(pose: np.ndarray) -> np.ndarray:
    pose = np.asarray(pose, dtype=np.float64)
    rest = _body()[0]
    hip = np.array([0.0, HIP_HEIGHT, 0.0])
    legs = smoothstep((HIP_HEIGHT + 0.02 - rest[:, 1]) / 0.14)[:, None]
    points = rest + legs * ((rest - hip) @ _leg_swing(pose).T + hip - rest)
    waist = np.array([0.0, 0.5 * HEIGHT, 0.0])
    return (points - waist) @ _tilt(pose).T + waist
