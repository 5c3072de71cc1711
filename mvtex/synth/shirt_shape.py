"""The built-in T-shirt at rest, and the mannequin that wears it (DESIGN §8).

Meters, y up, the front facing +z; the mannequin stands with its arms lowered about 28
degrees below horizontal. The shirt is sewn from two T-shaped pattern pieces, front and
back, each a torso with half of each short sleeve, joined at the side seams, the under-arm
seams and the shoulder seams that run on along the top of the sleeves; it is open at the
collar, the waist and the sleeve ends. Pattern coordinates (a, h), meters of material, are
the material coordinates: a across (front: growing towards +x, back: towards -x, so each
piece reads left to right seen from its outside), h up. The uv atlas is the two pieces
scaled by one factor, front above back.

The rest shape has three parts:

* the lower torso (h below `YOKE_BOTTOM`): an elliptic cylinder, a = arc length around the
  section from the front centre; unrolled without distortion, so (alpha, h) with alpha = a
  on the front and P/2 + a on the back is one chart around the whole torso (`torso_point`);
* the sleeves (|a| beyond `HALF_WIDTH`): circular tubes around the lowered arms, a - HALF_WIDTH
  along the arm and h around it, unrolled without distortion as well (`sleeve_point`);
* the yoke between them (shoulders, neckline, the top of the chest and back): given on its
  borders (seams, neckline, the sides of the torso and sleeves) and filled by the smoothest
  surface through them (a bi-Laplacian on the pattern mesh of both pieces, sewn, so the
  surface is smooth across the shoulder seams too).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.integrate import cumulative_trapezoid

from mvtex.synth.mannequin import ellipsoid, elliptic_stack, mesh_implicit, round_cone, smooth_min
from mvtex.synth.pattern import mesh_pattern, sample_curve

SEMI_X, SEMI_Z = 0.19, 0.125  # the lower torso's elliptic section, m


HEM = -0.33  # height of the waist hem, m


YOKE_BOTTOM = 0.06  # where the lower torso meets the yoke


ARMPIT_HEIGHT = 0.11


ARM_ANGLE = np.radians(62.0)  # rest angle of the arms from the vertical


SLEEVE_RADIUS = 0.056


SLEEVE_LENGTH = 0.15  # along the arm, from the armpit's section to the sleeve end


SPACING = 0.0135  # triangle edge length of the pattern meshes, m


_NECK_HALF_WIDTH = 0.07  # the neck hole in the pattern: half width and depth / half width
_NECK_DEPTH = {True: 1.2, False: 0.9}


_NECKLINE_RADIUS, _NECK_CORNER_HEIGHT = 0.072, 0.30  # the neckline in 3-D, around the neck
_NECKLINE_DIP = {True: 0.045, False: 0.012}  # how far the neckline drops at the front / back centre


_SHOULDER_RISE = 0.05  # pattern height of the shoulder seam at the neck above the shoulder point


_SHOULDER_SLOPE = np.radians(20.0)  # the shoulder seam leaves the neck this far below horizontal


UV_SCALE = 0.7  # uv units per meter of material


_UV_V0 = {True: 0.52, False: 0.02}  # chart placement: front above back


# The arm at +x; the one at -x is its mirror image.
ARM_DIRECTION = np.array([np.sin(ARM_ANGLE), -np.cos(ARM_ANGLE), 0.0])
ARM_UP = np.array([np.cos(ARM_ANGLE), np.sin(ARM_ANGLE), 0.0])  # perpendicular to the arm, upwards
_Z = np.array([0.0, 0.0, 1.0])


@lru_cache(maxsize=1)
def _ellipse_table() -> tuple[np.ndarray, np.ndarray]:
    """Angle theta and arc length from the front centre, for (SEMI_X sin theta, SEMI_Z cos theta)."""
    theta = np.linspace(0.0, 2.0 * np.pi, 8193)
    return theta, cumulative_trapezoid(np.hypot(SEMI_X * np.cos(theta), SEMI_Z * np.sin(theta)), theta, initial=0.0)


PERIMETER = float(_ellipse_table()[1][-1])  # of the lower torso
HALF_WIDTH = PERIMETER / 4  # |a| of the side seams
ARMPIT = np.array([SEMI_X, ARMPIT_HEIGHT, 0.0])
SLEEVE_AXIS = ARMPIT + SLEEVE_RADIUS * ARM_UP  # the sleeve's axis starts here, along ARM_DIRECTION
SHOULDER_POINT = ARMPIT + 2.0 * SLEEVE_RADIUS * ARM_UP
SLEEVE_HALF_AROUND = np.pi * SLEEVE_RADIUS  # pattern height of the sleeves
SLEEVE_TOP = ARMPIT_HEIGHT + SLEEVE_HALF_AROUND  # pattern h of the seam along the top of the sleeves
_NECK_TOP = SLEEVE_TOP + _SHOULDER_RISE  # pattern h of the shoulder seam at the neck
_UV_U0 = 0.5 - UV_SCALE * (HALF_WIDTH + SLEEVE_LENGTH)


def torso_point(alpha: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Rest points (m,3) of the lower torso chart: arc length alpha around the section
    from the front centre (towards +x there; any real, it wraps), height h."""
    theta, arc = _ellipse_table()
    t = np.interp(np.mod(alpha, PERIMETER), arc, theta)
    return np.stack([SEMI_X * np.sin(t), h, SEMI_Z * np.cos(t)], axis=1)


def sleeve_point(u: np.ndarray, c: np.ndarray, side: float) -> np.ndarray:
    """Rest points (m,3) of a sleeve chart: u along the arm from the armpit's section, c arc
    length around it from the seam on top (front: 0 < c < pi R, back: -pi R < c < 0).

    Args:
        side: +1 for the arm at +x, -1 for its mirror image.
    """
    angle = np.asarray(c) / SLEEVE_RADIUS
    points = (SLEEVE_AXIS + np.asarray(u)[:, None] * ARM_DIRECTION
              + SLEEVE_RADIUS * (np.cos(angle)[:, None] * ARM_UP + np.sin(angle)[:, None] * _Z))
    return points * np.array([side, 1.0, 1.0])


@lru_cache(maxsize=1)
def _shoulder_seam() -> tuple[np.ndarray, np.ndarray]:
    """The shoulder seam in 3-D (in z = 0, x > 0) from the neck to the shoulder point: a
    cubic leaving the neck at `_SHOULDER_SLOPE` and arriving along the arm, as (k,2) points
    (x, y) and their arc length fractions."""
    start = np.array([_NECKLINE_RADIUS, _NECK_CORNER_HEIGHT])
    end = SHOULDER_POINT[:2]
    tangent = np.linalg.norm(end - start)
    s = np.linspace(0.0, 1.0, 2001)[:, None]
    curve = ((2 * s**3 - 3 * s**2 + 1) * start + (s**3 - 2 * s**2 + s) * tangent * np.array(
        [np.cos(_SHOULDER_SLOPE), -np.sin(_SHOULDER_SLOPE)]) + (-2 * s**3 + 3 * s**2) * end
             + (s**3 - s**2) * tangent * ARM_DIRECTION[:2])
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(curve, axis=0), axis=1))])
    return curve, arc / arc[-1]


def _shoulder_point_3d(a: np.ndarray, front: bool) -> np.ndarray:
    """The shoulder seam at pattern column a (neck half width <= |a| <= HALF_WIDTH)."""
    curve, fraction = _shoulder_seam()
    f = (np.abs(a) - _NECK_HALF_WIDTH) / (HALF_WIDTH - _NECK_HALF_WIDTH)
    x = np.interp(f, fraction, curve[:, 0]) * np.sign(a) * (1.0 if front else -1.0)
    return np.stack([x, np.interp(f, fraction, curve[:, 1]), np.zeros_like(x)], axis=1)


def _neckline_3d(a: np.ndarray, front: bool) -> np.ndarray:
    """The neckline at pattern column a (|a| <= neck half width): half a circle around the
    neck, dipping towards the front (back) centre."""
    psi = np.arcsin(np.clip(a / _NECK_HALF_WIDTH, -1.0, 1.0))
    sign = 1.0 if front else -1.0
    return np.stack([sign * _NECKLINE_RADIUS * np.sin(psi), _NECK_CORNER_HEIGHT - _NECKLINE_DIP[front] * np.cos(psi),
                     sign * _NECKLINE_RADIUS * np.cos(psi)], axis=1)


def _boundary(front: bool) -> tuple[np.ndarray, np.ndarray]:
    """A pattern piece's border, counter-clockwise: (b,2) samples and (b,) kinds
    (0 free edge, 1 side seam, 2 under-arm seam, 3 shoulder and sleeve-top seam, 4 neckline);
    a corner where a seam ends is a seam point."""
    w, top, arm = HALF_WIDTH, SLEEVE_TOP, ARMPIT_HEIGHT
    end, neck = HALF_WIDTH + SLEEVE_LENGTH, _NECK_HALF_WIDTH
    psi = np.linspace(0.5 * np.pi, -0.5 * np.pi, 400)
    neckline = np.stack([neck * np.sin(psi), _NECK_TOP - _NECK_DEPTH[front] * neck * np.cos(psi)], axis=1)
    pieces = [([(-w, HEM), (w, HEM)], 0), ([(w, HEM), (w, arm)], 1), ([(w, arm), (end, arm)], 2),
              ([(end, arm), (end, top)], 0), ([(end, top), (w, top), (neck, _NECK_TOP)], 3), (neckline, 4),
              ([(-neck, _NECK_TOP), (-w, top), (-end, top)], 3), ([(-end, top), (-end, arm)], 0),
              ([(-end, arm), (-w, arm)], 2), ([(-w, arm), (-w, HEM)], 1)]
    points, kinds = [], []
    for k, (corners, kind) in enumerate(pieces):
        corners = np.asarray(corners, np.float64)
        if len(corners) < 50:  # a polyline: sample each straight piece on its own
            samples = np.concatenate([sample_curve(np.linspace(p, q, 50), SPACING)
                                      for p, q in zip(corners[:-1], corners[1:])])
        else:
            samples = sample_curve(corners, SPACING)
        kind_of = np.full(len(samples), kind)
        if pieces[k - 1][1] in (1, 2, 3) and kind not in (1, 2, 3):
            kind_of[0] = pieces[k - 1][1]
        points.append(samples)
        kinds.append(kind_of)
    return np.concatenate(points), np.concatenate(kinds)


@dataclass(frozen=True)
class Pattern:
    """The two pattern pieces meshed and sewn.

    Attributes:
        faces: (m,3) int32 over all vertices (front piece first), counter-clockwise seen
            from outside.
        points: (n,2) float64 pattern coordinates (a, h) per vertex.
        front: (n,) bool, the vertex's piece.
        distinct: (n,) int64, the vertex's point of the sewn garment (seam copies share one).
        rest: (d,3) float64 rest positions of the d distinct points.
    """

    faces: np.ndarray
    points: np.ndarray
    front: np.ndarray
    distinct: np.ndarray
    rest: np.ndarray


def _cotangent_laplacian(points: np.ndarray, faces: np.ndarray, ids: np.ndarray, n: int):
    """(n,n) cotangent Laplacian of a flat mesh (points (p,2)), its vertices renamed by ids."""

    corner = points[faces]
    rows, cols, values = [], [], []
    for k in range(3):
        u = corner[:, (k + 1) % 3] - corner[:, k]
        v = corner[:, (k + 2) % 3] - corner[:, k]
        cot = 0.5 * np.einsum("ij,ij->i", u, v) / np.abs(u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0])
        i, j = ids[faces[:, (k + 1) % 3]], ids[faces[:, (k + 2) % 3]]
        rows += [i, j, i, j]
        cols += [j, i, i, j]
        values += [cot, cot, -cot, -cot]
    return sp.csr_matrix((np.concatenate(values), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))


@lru_cache(maxsize=1)
def pattern() -> Pattern:
    """The meshed, sewn pattern and its rest shape (computed once per process)."""

    pieces = []
    for front in (True, False):
        boundary, kinds = _boundary(front)
        points, faces = mesh_pattern(boundary, SPACING)
        pieces.append((points, faces, np.concatenate([kinds, np.full(len(points) - len(boundary), -1)]), front))
    # Sew: the back's seam point (a, h) is the front's (-a, h).
    (front_points, front_faces, front_kinds, _), (back_points, back_faces, back_kinds, _) = pieces
    nf = len(front_points)
    seam = {(round(-front_points[i, 0], 9), round(front_points[i, 1], 9)): i for i in np.flatnonzero(front_kinds > 0)}
    back_ids = nf + np.arange(len(back_points))
    for j in np.flatnonzero(np.isin(back_kinds, (1, 2, 3))):
        back_ids[j] = seam[(round(back_points[j, 0], 9), round(back_points[j, 1], 9))]
    _, distinct = np.unique(np.concatenate([np.arange(nf), back_ids]), return_inverse=True)
    distinct = distinct.reshape(-1)
    n = distinct.max() + 1
    points = np.concatenate([front_points, back_points])
    kinds = np.concatenate([front_kinds, back_kinds])
    front = np.arange(len(points)) < nf
    faces = np.concatenate([front_faces, back_faces + nf])
    # Known rest points: the lower torso, the sleeves, the seams and the neckline of the yoke.
    rest = np.zeros((n, 3))
    known = np.zeros(n, bool)
    free_edge = np.zeros(n, bool)
    for piece in (True, False):
        mine = np.flatnonzero(front == piece)
        a, h, kind, ids = points[mine, 0], points[mine, 1], kinds[mine], distinct[mine]
        sleeve = np.abs(a) > HALF_WIDTH + 1e-12
        torso = ~sleeve & (h <= YOKE_BOTTOM + 1e-12)
        side = (kind == 1) & ~torso
        shoulder = (kind == 3) & ~sleeve
        neck = kind == 4
        side_of = np.sign(a) * (1.0 if piece else -1.0)
        u, c = np.abs(a) - HALF_WIDTH, (SLEEVE_TOP - h) * (1.0 if piece else -1.0)
        rest[ids[torso]] = torso_point(np.where(piece, a, 0.5 * PERIMETER + a)[torso], h[torso])
        for s in (-1.0, 1.0):
            pick = sleeve & (side_of == s)
            rest[ids[pick]] = sleeve_point(u[pick], c[pick], s)
        rest[ids[side]] = np.stack([side_of[side] * SEMI_X, h[side], np.zeros(side.sum())], axis=1)
        rest[ids[shoulder]] = _shoulder_point_3d(a[shoulder], piece)
        rest[ids[neck]] = _neckline_3d(a[neck], piece)
        known[ids[torso | sleeve | side | shoulder | neck]] = True
        free_edge[ids[(kind == 0) | neck]] = True
    # The yoke: the smoothest surface through all that (min |L x|^2, L the pattern's
    # cotangent Laplacian of the sewn pieces, on every point not on a free edge).
    laplacian = (_cotangent_laplacian(front_points, front_faces, distinct[:nf], n)
                 + _cotangent_laplacian(back_points, back_faces, distinct[nf:], n))[np.flatnonzero(~free_edge)]
    unknown, given = np.flatnonzero(~known), np.flatnonzero(known)
    lu, lk = laplacian[:, unknown], laplacian[:, given]
    rest[unknown] = spla.spsolve((lu.T @ lu).tocsc(), -(lu.T @ (lk @ rest[given])))
    return Pattern(faces=faces.astype(np.int32), points=points, front=front, distinct=distinct.astype(np.int64),
                   rest=rest)


def pattern_to_uv(points: np.ndarray, front: np.ndarray) -> np.ndarray:
    """(n,2) uv of pattern points (n,2) on the front (True) or back piece."""
    v0 = np.where(front, _UV_V0[True], _UV_V0[False])
    return np.stack([_UV_U0 + UV_SCALE * (points[:, 0] + HALF_WIDTH + SLEEVE_LENGTH),
                     v0 + UV_SCALE * (points[:, 1] - HEM)], axis=1)


def uv_to_pattern(uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The inverse of `pattern_to_uv`: ((n,2) pattern points, (n,) front)."""
    uv = np.asarray(uv, np.float64)
    front = uv[:, 1] >= 0.5
    v0 = np.where(front, _UV_V0[True], _UV_V0[False])
    return np.stack([(uv[:, 0] - _UV_U0) / UV_SCALE - HALF_WIDTH - SLEEVE_LENGTH,
                     (uv[:, 1] - v0) / UV_SCALE + HEM], axis=1), front


# -- the mannequin -----------------------------------------------------------------------------

_TORSO_PROFILE = np.array([  # y, semi-axis x, semi-axis z (m)
    [-0.43, 0.160, 0.101], [-0.33, 0.168, 0.107], [-0.20, 0.158, 0.101], [-0.10, 0.150, 0.096],
    [0.00, 0.155, 0.101], [0.08, 0.152, 0.103], [0.15, 0.145, 0.094], [0.225, 0.135, 0.082]])


SHOULDER_JOINT = SLEEVE_AXIS - 0.035 * ARM_DIRECTION  # the arm at +x turns about this point


_ARM_LENGTH = 0.035 + SLEEVE_LENGTH + 0.035  # from the joint; ends 3.5 cm past the sleeve


def mannequin_implicit(points: np.ndarray) -> np.ndarray:
    """(n,) implicit function of the mannequin at rest (negative inside): torso, neck, the
    shoulders and the upper arms, smoothly joined."""
    d = elliptic_stack(points, _TORSO_PROFILE, 0.06)
    d = smooth_min(d, round_cone(points, (0.0, 0.17, -0.005), (0.0, 0.355, 0.0), 0.051, 0.049), 0.04)
    for side in (1.0, -1.0):
        mirror = np.array([side, 1.0, 1.0])
        joint = SHOULDER_JOINT * mirror
        d = smooth_min(d, ellipsoid(points, (SHOULDER_JOINT - 0.004 * ARM_UP) * mirror, (0.046, 0.042, 0.04)), 0.05)
        d = smooth_min(d, round_cone(points, joint, joint + _ARM_LENGTH * ARM_DIRECTION * mirror, 0.042, 0.041), 0.03)
    return d


@lru_cache(maxsize=1)
def mannequin() -> tuple[np.ndarray, np.ndarray]:
    """The mannequin at rest: vertices (nb,3) float64 and faces (mb,3) int32, outward."""
    return mesh_implicit(mannequin_implicit, (-0.47, -0.47, -0.16), (0.47, 0.44, 0.16), 0.024)
