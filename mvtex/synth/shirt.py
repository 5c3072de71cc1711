"""The built-in T-shirt, worn (DESIGN §8): its poses, folds and ground-truth shapes, and the
mannequin under it in the same pose (the shape at rest: `mvtex.synth.shirt_shape`).

A pose vector (POSE_DIM numbers in [-1, 1]) drives one smooth warp of space that moves the
mannequin and the shirt alike (`pose_warp`):

* the arms turn about their shoulder joints (arm lift), the shoulders rise (shrug), both
  blended into the torso over the shoulder and the armpit;
* the spine bends forward or back, sideways and twists, like a rod whose sections follow
  a frame rotating with height (the arms ride on the frame of their shoulders).

On top of it the cloth folds (`mvtex.synth.folds`): compression folds on the front or back
when the body bends, diagonal folds when it twists, side folds, and folds around the
sleeves near the shoulder when an arm lifts (on top) or lowers (underneath); their
position, direction, depth and wavelength depend nonlinearly on the pose. The lower torso's
cloth also rides around the body. Every fold gathers material towards itself, so the
hem and the sleeve ends move up, never the seams.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy.integrate import cumulative_trapezoid
from scipy.special import expit, ndtr

from mvtex.synth import shirt_shape as shape
from mvtex.synth.folds import Fold, fold_field, mix, smoothstep, wrap

POSE_DIM = 14


ARM_LIFT = np.radians(12.0)  # the arms turn by ARM_LIFT * pose[5], pose[6] (radians)


_SHRUG = 0.015  # most the shoulders rise, m


_SPINE_GRID = np.linspace(-0.5, 0.5, 321)  # heights of the spine frames (0 at index 160)


_RIDE_FADE = (-0.25, 0.04)  # the torso's cloth rides fully below, not at all above


def make_garment() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rest T-shirt.

    Returns:
        faces: (m, 3) int32, counter-clockwise seen from outside.
        uv: (n, 2) float32 in [0, 1]^2: the front piece in v > 0.5, the back in v < 0.5,
            each its pattern scaled by `shirt_shape.UV_SCALE`.
        rest: (n, 3) float32 rest positions in meters; the copies of a seam vertex share
            one position.
    """
    p = shape.pattern()
    uv = shape.pattern_to_uv(p.points, p.front)
    return p.faces.copy(), uv.astype(np.float32), p.rest[p.distinct].astype(np.float32)


def make_body() -> tuple[np.ndarray, np.ndarray]:
    """The mannequin at rest: faces (mb,3) int32 (outward) and vertices (nb,3) float32."""
    vertices, faces = shape.mannequin()
    return faces.copy(), vertices.astype(np.float32)


def sample_poses(num_poses: int, seed: int) -> np.ndarray:
    """Pose vectors, uniform in [-1, 1].

    Components: 0 forward(+)/back bend, 1 side bend (+ leans towards -x), 2 twist, 3 and 4
    the shrug of the shoulder at -x and at +x, 5 and 6 the lift of the arm at -x and at +x
    (by ARM_LIFT radians at 1), 7..13 modulate the folds' position, direction, depth and
    wavelength, where the spine bends, and how the cloth rides (nonlinearly).

    Returns:
        (num_poses, POSE_DIM) float32.
    """
    rng = np.random.default_rng(seed)
    return rng.uniform(-1.0, 1.0, size=(num_poses, POSE_DIM)).astype(np.float32)


def _arm_frame(points: np.ndarray, side: float) -> tuple[np.ndarray, np.ndarray]:
    """(u, rho) of points in the frame of the sleeve of the arm at `side`: u along the arm
    from the armpit's section, rho the distance from its axis."""
    rel = points * np.array([side, 1.0, 1.0]) - shape.SLEEVE_AXIS
    u = rel @ shape.ARM_DIRECTION
    return u, np.linalg.norm(rel - u[:, None] * shape.ARM_DIRECTION, axis=1)


def _weights(points: np.ndarray) -> np.ndarray:
    """(n, 5) blend weights of rest points: the turn of each arm (at -x, at +x), the frame
    each arm rides on (same order), and the shrug of the shoulders.

    An arm turns with its sleeve from a little before the armpit's section on, less away
    from its axis (the side of the torso below the armpit follows a little, stretching as
    cloth does there); it rides on the spine frame of its shoulder only beyond the armpit.
    """
    out = np.empty((len(points), 5))
    for k, side in enumerate((-1.0, 1.0)):
        u, rho = _arm_frame(points, side)
        out[:, k] = smoothstep((u + 0.06) / 0.12) * (1.0 - smoothstep((rho - 0.06) / 0.07))
        out[:, 2 + k] = smoothstep(u / 0.1) * (1.0 - smoothstep((rho - 0.06) / 0.04))
    out[:, 4] = smoothstep((np.abs(points[:, 0]) - 0.07) / 0.1) * smoothstep((points[:, 1] - 0.02) / 0.12)
    return out


class PoseWarp:
    """The smooth warp of space of one pose (module docstring), for rest points of the
    mannequin and of the shirt alike."""

    def __init__(self, pose: np.ndarray):
        p = np.asarray(pose, dtype=np.float64)
        g = _SPINE_GRID
        # Bends have a Gaussian curvature profile around a pose-dependent height and the
        # frame at height 0 is held fixed, which keeps the body centred.
        bend = 0.24 * p[0] + 0.05 * p[0] ** 2
        bend_at = -0.06 + 0.06 * np.sin(np.pi * (p[7] + 0.3 * p[0]))
        side_at = -0.02 + 0.05 * np.cos(np.pi * p[9])
        ax = bend * (ndtr((g - bend_at) / 0.2) - ndtr(-bend_at / 0.2))
        az = 0.16 * p[1] * (ndtr((g - side_at) / 0.2) - ndtr(-side_at / 0.2))
        tw = (0.35 * p[2] + 0.08 * p[0] * p[1]) * g / 0.64
        axis_y = np.stack([-np.sin(az), np.cos(az) * np.cos(ax), np.cos(az) * np.sin(ax)], 1)
        centre = cumulative_trapezoid(axis_y, g, axis=0, initial=0.0)
        self._frames = np.column_stack([np.cos(tw), np.sin(tw), np.cos(az), np.sin(az), np.cos(ax), np.sin(ax),
                                        centre - centre[160]])
        self._shrug = _SHRUG * (0.5 + 0.5 * p[3:5])
        self._turn = [_turn_about(shape.SHOULDER_JOINT * np.array([side, 1.0, 1.0]), side * ARM_LIFT * p[5 + k])
                      for k, side in enumerate((-1.0, 1.0))]

    def __call__(self, rest: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
        """Posed points (n,3) float64 of rest points (n,3); `weights`: `_weights(rest)` when
        already known."""
        rest = np.asarray(rest, dtype=np.float64)
        w = _weights(rest) if weights is None else weights
        out = rest.copy()
        for k, side in enumerate((-1.0, 1.0)):
            rotation, joint = self._turn[k]
            out += w[:, k : k + 1] * ((rest - joint) @ rotation.T + joint - rest)
            on_side = np.sign(rest[:, 0]) == side
            out[:, 1] += np.where(on_side, np.maximum(w[:, 4], w[:, k]), 0.0) * self._shrug[k]
        attach = np.maximum(w[:, 2], w[:, 3])
        height = (1.0 - attach) * rest[:, 1] + attach * shape.SHOULDER_JOINT[1]
        return self._spine(out, height)

    def _spine(self, points: np.ndarray, height: np.ndarray) -> np.ndarray:
        """Points carried by the spine frames at `height` (points are offsets from the axis there)."""
        g0, step = _SPINE_GRID[0], _SPINE_GRID[1] - _SPINE_GRID[0]
        f = (height - g0) / step
        i = np.clip(np.floor(f).astype(np.intp), 0, len(_SPINE_GRID) - 2)
        t = np.clip(f - i, 0.0, 1.0)[:, None]
        frame = self._frames[i] * (1.0 - t) + self._frames[i + 1] * t
        cos_tw, sin_tw, cos_az, sin_az, cos_ax, sin_ax, cx, cy, cz = frame.T
        x, y, z = points[:, 0], points[:, 1] - height, points[:, 2]
        x, z = x * cos_tw + z * sin_tw, z * cos_tw - x * sin_tw
        x, y = x * cos_az - y * sin_az, x * sin_az + y * cos_az
        y, z = y * cos_ax - z * sin_ax, y * sin_ax + z * cos_ax
        return np.stack([x + cx, y + cy, z + cz], axis=1)


def _turn_about(joint: np.ndarray, angle: float) -> tuple[np.ndarray, np.ndarray]:
    """(rotation about z by angle, joint)."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), np.asarray(joint, np.float64)


def pose_warp(pose: np.ndarray) -> PoseWarp:
    """The warp of one pose: `pose_warp(pose)(rest_points)` -> posed points."""
    return PoseWarp(pose)


def pose_body(pose: np.ndarray) -> np.ndarray:
    """The mannequin in one pose, (nb,3) float32 in `make_body`'s vertex order."""
    return _posed_body(pose).astype(np.float32)


def _posed_body(pose: np.ndarray) -> np.ndarray:
    vertices, _ = shape.mannequin()
    return PoseWarp(pose)(vertices, _body_weights())


@lru_cache(maxsize=1)
def _body_weights() -> np.ndarray:
    return _weights(shape.mannequin()[0])


# -- folds ---------------------------------------------------------------------------------------


def _folds(p: np.ndarray) -> list[Fold]:
    """Fold templates of a pose, each gated by its driver (bend, twist, side bend, arm lift).

    Torso folds live on the chart (alpha, h) of the lower torso, sleeve folds on the chart
    (u, c) of a sleeve; their +n side points towards the yoke, which stays in place.
    """
    m = p[7:14]
    pi = np.pi
    q = shape.PERIMETER / 4
    twist_dir = np.tanh(3.0 * p[2])  # smooth flip of the diagonal with the twist's sign
    # Gates rise smoothly from exactly 0, so a fold is absent until its driver passes a threshold.
    forward, backward = smoothstep((p[0] + 0.1) / 0.6), smoothstep((0.1 - p[0]) / 0.6)
    towards_minus_x, towards_plus_x = smoothstep(p[1] / 0.6), smoothstep(-p[1] / 0.6)
    twist = smoothstep((abs(p[2]) - 0.05) / 0.5)
    # A panel holds one large fold system at a time: where a bend compresses a panel its
    # twist folds give way, since two steep folds crossing cannot both keep lengths.
    front_twist, back_twist = twist * (1 - forward), twist * (1 - backward)
    folds = [
        # Horizontal compression folds on the front when bending forward; tilted by side bend.
        Fold("torso", 0.05 * np.sin(pi * m[2]) - 0.04 * p[1], -0.17 + 0.04 * np.cos(pi * m[1] + 0.5 * p[0]),
             pi / 2 + 0.25 * p[1] + 0.12 * np.sin(pi * m[3]), 0.06 + 0.02 * mix(pi * m[3] + m[0]),
             forward * (1.2 + 0.85 * mix(pi * m[0] + 0.7 * m[1])), 0.45, 0.25),
        # The same on the back when bending backward.
        Fold("torso", 2 * q + 0.05 * np.sin(pi * m[5]), -0.16 + 0.04 * np.sin(pi * m[0] - m[1]),
             pi / 2 - 0.2 * p[1] + 0.1 * np.cos(pi * m[6]), 0.065 + 0.02 * mix(pi * m[2] + m[3]),
             backward * (0.9 + 0.75 * mix(pi * m[4])), 0.45, 0.25),
        # Diagonal twist folds, front and back, along the direction the twist compresses.
        Fold("torso", 0.06 * m[5] + 0.03 * np.sin(pi * m[2]), -0.17 + 0.03 * np.sin(pi * m[4]),
             pi / 2 + 0.45 * twist_dir + 0.06 * m[4], 0.06 + 0.025 * expit(3 * m[5] - m[6]),
             front_twist * (0.8 + 0.8 * mix(pi * m[6] + 2 * p[2])), 0.45, 0.24),
        Fold("torso", 2 * q + 0.06 * np.sin(pi * m[6]), -0.17 - 0.03 * np.cos(pi * m[3]),
             pi / 2 + 0.42 * twist_dir - 0.06 * m[3], 0.065 + 0.02 * mix(pi * m[1] - p[2]),
             back_twist * (0.7 + 0.5 * mix(pi * m[0] * m[4])), 0.45, 0.22),
        # Side folds on the side a side bend compresses, across the side seams.
        Fold("torso", -q - 0.02 + 0.03 * m[6], -0.15 + 0.04 * np.sin(pi * m[5] + p[1]),
             pi / 2 + 0.2 * np.sin(pi * m[0]), 0.05 + 0.015 * mix(pi * m[4]),
             towards_minus_x * (0.85 + 0.45 * mix(pi * m[3] - m[4])), 0.45, 0.12),
        Fold("torso", q + 0.02 - 0.03 * m[5], -0.16 + 0.04 * np.cos(pi * m[6] - p[1]),
             pi / 2 - 0.2 * np.sin(pi * m[1]), 0.05 + 0.015 * mix(pi * m[2] * m[3]),
             towards_plus_x * (0.85 + 0.45 * mix(pi * m[6])), 0.45, 0.12),
    ]
    for k, chart in enumerate(("sleeve-", "sleeve+")):
        lift = p[5 + k]
        # A lifted arm crowds the top of its sleeve near the shoulder; a lowered one, the underside.
        folds.append(Fold(chart, 0.075 + 0.012 * np.sin(pi * m[k + 2] + lift), 0.01 * m[k],
                          pi + 0.25 * np.sin(pi * m[4 + k]), 0.045 + 0.012 * mix(pi * m[1 + k] - p[3 + k]),
                          smoothstep((lift - 0.1) / 0.6) * (1.0 + 0.5 * mix(pi * m[k] + 2 * lift)), 0.35, 0.10))
        folds.append(Fold(chart, 0.075 + 0.012 * np.cos(pi * m[k + 3]), shape.SLEEVE_HALF_AROUND + 0.015 * m[6 - k],
                          pi - 0.25 * np.sin(pi * m[5 - k]), 0.045 + 0.012 * mix(pi * m[k + 4]),
                          smoothstep((-lift - 0.1) / 0.6) * (0.9 + 0.5 * mix(pi * m[2 - k] - lift)), 0.35, 0.09))
    return folds


class _Material:
    """The distinct material points of a garment's vertices and their charts.

    Attributes:
        rest: (d,3) float64 distinct rest points; inverse: (n,) vertex -> distinct point.
        weights: (d,5) `_weights(rest)`.
        torso: indices of the points on the lower torso, with their chart (alpha, h).
        sleeves: {chart name: (indices, u, c, side)}.
    """

    def __init__(self, rest: np.ndarray, uv: np.ndarray):
        rest = np.asarray(rest)
        _, first, inverse = np.unique(rest, axis=0, return_index=True, return_inverse=True)
        points, front = shape.uv_to_pattern(np.asarray(uv)[first])
        a, h = points[:, 0], points[:, 1]
        self.rest = rest[first].astype(np.float64)
        self.inverse = inverse.reshape(-1)
        self.weights = _weights(self.rest)
        sleeve = np.abs(a) > shape.HALF_WIDTH + 1e-6
        self.torso = np.flatnonzero(~sleeve & (h <= shape.YOKE_BOTTOM))
        self.alpha = np.where(front, a, 0.5 * shape.PERIMETER + a)[self.torso]
        self.h = h[self.torso]
        side = np.where(front, np.sign(a), -np.sign(a))
        self.sleeves = {}
        for chart, s in (("sleeve-", -1.0), ("sleeve+", 1.0)):
            idx = np.flatnonzero(sleeve & (side == s))
            c = (shape.SLEEVE_TOP - h[idx]) * np.where(front[idx], 1.0, -1.0)
            self.sleeves[chart] = (idx, np.abs(a[idx]) - shape.HALF_WIDTH, c, s)


def _torso_fade(fold: Fold):
    """Fade of a torso fold along its ridge: out before its +n reach meets the yoke, and
    before the hem."""
    n = fold.normal
    ceiling = shape.YOKE_BOTTOM - 0.01 - fold.reach * abs(n[1])

    def fade(tau):
        ridge = fold.q0 + tau * n[0]
        return smoothstep((ceiling - ridge) / 0.05) * smoothstep((ridge - shape.HEM - 0.03) / 0.05)

    return fade


def _posed_chart(warp: PoseWarp, chart_point, p: np.ndarray, q: np.ndarray, orient: float):
    """Posed points (m,3) of chart coordinates and the unit normals of the posed chart
    surface there (forward differences, `orient` * d/dp x d/dq)."""
    eps, m = 1e-5, len(p)
    x = warp(chart_point(np.concatenate([p, p + eps, p]), np.concatenate([q, q, q + eps])))
    normal = orient * np.cross(x[m : 2 * m] - x[:m], x[2 * m :] - x[:m])
    return x[:m], normal / np.linalg.norm(normal, axis=1, keepdims=True)


def _deform_material(material: _Material, pose: np.ndarray) -> tuple[np.ndarray, list[tuple]]:
    """Ground-truth positions (d,3) float64 of the distinct points of `material`, and per
    fold a tuple (depth = peak-to-trough normal offset in m, wavelength, peak angle)."""
    pose = np.asarray(pose, dtype=np.float64)
    warp = PoseWarp(pose)
    out = warp(material.rest, material.weights)
    info = []
    # The torso's cloth rides around the body and up and down on it, fading out below the yoke.
    fade = 1.0 - smoothstep((material.h - _RIDE_FADE[0]) / (_RIDE_FADE[1] - _RIDE_FADE[0]))
    slides = {"torso": np.stack([0.012 * np.sin(np.pi * pose[11] + 0.5 * pose[2]) * fade,
                                 0.006 * np.cos(np.pi * pose[13]) * fade], axis=1)}
    offsets = {"torso": np.zeros(len(material.torso))}
    for chart, (idx, _, _, _) in material.sleeves.items():
        slides[chart], offsets[chart] = np.zeros((len(idx), 2)), np.zeros(len(idx))
    for fold in _folds(pose):
        if fold.phi_max == 0.0:  # gated off
            info.append((0.0, fold.wavelength, 0.0))
            continue
        if fold.chart == "torso":
            dp, dq = wrap(material.alpha - fold.p0, shape.PERIMETER), material.h - fold.q0
            support, slide, offset, peak = fold_field(fold, dp, dq, _torso_fade(fold))
        else:
            _, u, c, _ = material.sleeves[fold.chart]
            dq = wrap(c - fold.q0, 2 * shape.SLEEVE_HALF_AROUND)
            support, slide, offset, peak = fold_field(fold, u - fold.p0, dq)
        slides[fold.chart][support] += slide
        offsets[fold.chart][support] += offset
        info.append((float(np.ptp(offset)) if len(offset) else 0.0, fold.wavelength, peak))
    charts = {"torso": (material.torso, material.alpha, material.h, shape.torso_point, 1.0)}
    for chart, (idx, u, c, side) in material.sleeves.items():
        charts[chart] = (idx, u, c, lambda a, b, s=side: shape.sleeve_point(a, b, s), -side)
    for chart, (idx, p, q, chart_point, orient) in charts.items():
        slide, offset = slides[chart], offsets[chart]
        moved = np.flatnonzero(np.any(slide != 0.0, axis=1) | (offset != 0.0))
        if len(moved):
            x, normal = _posed_chart(warp, chart_point, p[moved] + slide[moved, 0], q[moved] + slide[moved, 1], orient)
            out[idx[moved]] = x + offset[moved, None] * normal
    return out, info


def deform(rest: np.ndarray, uv: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """The ground-truth shirt of one pose.

    Args:
        rest: (n, 3) rest positions and uv: (n, 2) texture coordinates, from `make_garment`
            (the material coordinates are read from them).
        pose: (POSE_DIM,) pose vector in [-1, 1].

    Returns:
        (n, 3) float32 positions; the copies of a seam vertex get identical positions.
    """
    material = _Material(rest, uv)
    return _deform_material(material, pose)[0][material.inverse].astype(np.float32)
