"""Novel cameras between the cameras of an array: view weights (parsed, checked, along a
segment or over a 2x2 grid) and the camera they make (centre and K blended, orientation by
weighted quaternion averaging).
"""

from __future__ import annotations

import numbers
from typing import Mapping, Sequence

import numpy as np
from scipy.optimize import nnls
from scipy.spatial.transform import Rotation, Slerp

from mvtex.data.camera import Camera, check_camera_name
from mvtex.data.rig import Rig, as_rig
from mvtex.util.errors import InputError, OptionError

WEIGHT_TOLERANCE = 1e-6
MAX_VIEWS = 4096  # views one call makes (each is a camera folder of the output set)


def parse_weights(text: str) -> dict[str, float]:
    """`"A=0.3,B=0.7"` -> {"A": 0.3, "B": 0.7}; InputError on malformed text."""
    weights: dict[str, float] = {}
    for item in str(text).split(","):
        item = item.strip()
        if not item:
            continue
        name, sep, value = item.partition("=")
        name = name.strip()
        try:
            w = float(value) if sep else float("nan")
        except ValueError:
            w = float("nan")
        if not name or not sep or not np.isfinite(w):
            raise OptionError("weights", f"hold {item!r}, which is not NAME=NUMBER (e.g. \"left=0.5,right=0.5\")")
        if name in weights:
            raise OptionError("weights", f"name camera {name!r} twice")
        weights[name] = w
    if not weights:
        raise OptionError("weights", "name no camera")
    return weights


def check_weights(weights: Mapping[str, float], rig: Rig) -> dict[str, float]:
    """Weights of a view, validated: a mapping camera name -> number, known cameras, finite,
    ≥ 0, summing to 1 (±1e-6)."""

    if not isinstance(weights, Mapping) or not weights:
        raise OptionError("weights", f"must map camera names to numbers, got {weights!r:.60}")
    if not all(isinstance(k, str) for k in weights) or not all(
            isinstance(w, numbers.Real) and not isinstance(w, bool) for w in weights.values()):
        raise OptionError("weights", f"must map camera names to numbers, got {dict(weights)!r:.80}")
    rig.select(list(weights))  # InputError naming unknown cameras
    values = np.array([float(w) for w in weights.values()], np.float64)
    if not np.all(np.isfinite(values)):
        raise OptionError("weights", f"must be finite numbers, got {dict(weights)}")
    if np.any(values < 0):
        raise OptionError("weights", f"must be >= 0, got {dict(weights)}")
    if abs(values.sum() - 1.0) > WEIGHT_TOLERANCE:
        raise OptionError("weights", f"must sum to 1 (within {WEIGHT_TOLERANCE:g}), they sum to {values.sum():.9g}")
    return {str(k): float(v) for k, v in weights.items()}


def between_weights(a: str, b: str, steps: int) -> list[dict[str, float]]:
    """`steps` views evenly along the segment a -> b, both ends included (t = i/(steps-1))."""
    if int(steps) < 2 or int(steps) > MAX_VIEWS:
        raise OptionError("steps", f"must be in 2..{MAX_VIEWS}, got {steps}")
    if a == b:
        raise OptionError("between", f"needs two different cameras, got {a},{b}")
    out = []
    for i in range(int(steps)):
        t = i / (int(steps) - 1)
        out.append({a: 1.0 - t, b: t})
    return out


def grid_weights(a: str, b: str, c: str, d: str, steps: int) -> list[dict[str, float]]:
    """steps × steps views bilinear over a 2×2 array, row-major from `a`.

    Corners: a at (row 0, column 0), b at (row 0, last column), c at (last row, column 0),
    d at (last row, last column); view (i, j) has s = j/(steps-1) along a->b and
    t = i/(steps-1) along a->c.
    """
    if int(steps) < 2 or int(steps) ** 2 > MAX_VIEWS:
        raise OptionError("steps", f"must be in 2..{int(MAX_VIEWS ** 0.5)} (steps x steps views), got {steps}")
    if len({a, b, c, d}) != 4:
        raise OptionError("grid", f"needs four different cameras, got {a},{b},{c},{d}")
    out = []
    n = int(steps)
    for i in range(n):
        t = i / (n - 1)
        for j in range(n):
            s = j / (n - 1)
            out.append({a: (1 - s) * (1 - t), b: s * (1 - t), c: (1 - s) * t, d: s * t})
    return out


def plan_views(*, weights: str | Mapping[str, float] | None = None, between: Sequence[str] | None = None,
               grid: Sequence[str] | None = None, steps: int | None = None,
               name: str | None = None) -> tuple[list[dict[str, float]], list[str]]:
    """The weights and names of the views `mvtex views` makes: one view of `weights`
    ("A=0.3,B=0.7" or a mapping) named `name` (default "view"); `steps` views along `between` (two cameras);
    or `steps` x `steps` views over `grid` (four cameras, row-major from the first), named
    view_000, view_001, ... Exactly one of weights, between and grid.

    Raises:
        OptionError: none or several of them, steps missing or given with weights, the wrong
            number of cameras.
    """
    given = [k for k, v in (("weights", weights), ("between", between), ("grid", grid)) if v is not None]
    if len(given) != 1:
        raise OptionError(None, f"weights, between or grid: give exactly one, got {', '.join(given) or 'none'}")
    if weights is not None:
        if steps is not None:
            raise OptionError("steps", "goes with between or grid, not with weights")
        return [parse_weights(weights) if isinstance(weights, str) else dict(weights)], [name or "view"]
    corners = list(between if between is not None else grid)
    kind, count = ("between", 2) if between is not None else ("grid", 4)
    if steps is None:
        raise OptionError("steps", f"is needed with {kind} (the number of views along it)")
    if len(corners) != count:
        raise OptionError(kind, f"needs {count} camera names, got {corners}")
    views = between_weights(*corners, steps) if count == 2 else grid_weights(*corners, steps)
    return views, view_names(len(views))


def view_names(count: int) -> list[str]:
    """view_000, view_001, ..."""
    return [f"view_{i:03d}" for i in range(count)]


def _single(weights: Mapping[str, float]) -> str | None:
    """The camera with weight exactly 1 (all others 0), if any."""
    ones = [k for k, w in weights.items() if w == 1.0]
    if len(ones) == 1 and all(w == 0.0 for k, w in weights.items() if k != ones[0]):
        return ones[0]
    return None


def interpolate_camera(rig: Rig, weights: Mapping[str, float], name: str) -> Camera:
    """The novel camera of `weights` over cameras of `rig` (see the module docstring).

    Args:
        rig: the array; weights: camera name -> weight (validated with `check_weights`).
        name: the new camera's name.

    Returns:
        Camera: width/height of the array cameras, K and centre blended, R averaged.

    Raises:
        InputError: the cameras' image sizes differ, or the weights are invalid.
    """

    rig = as_rig(rig)
    check_camera_name(name)
    weights = check_weights(weights, rig)
    one = _single(weights)
    if one is not None:
        return rig[one].with_name(name)
    used = [(rig[k], w) for k, w in weights.items() if w > 0]
    sizes = {(c.width, c.height) for c, _ in used}
    if len(sizes) > 1:
        raise InputError(None, "cameras " + ", ".join(c.name for c, _ in used) +
                         f" have different image sizes {sorted(sizes)}: a view can only blend cameras of one size")
    w = np.array([x for _, x in used], np.float64)
    w = w / w.sum()
    cams = [c for c, _ in used]
    centre = np.einsum("p,pi->i", w, np.stack([c.center for c in cams]))
    K = np.einsum("p,pij->ij", w, np.stack([c.K for c in cams]))
    K[1, 0], K[2] = 0.0, (0.0, 0.0, 1.0)  # exactly, where the weighted sum gives 0.9999999999999999
    dist = np.einsum("p,pi->i", w, np.stack([c.dist for c in cams]))
    rotations = Rotation.from_matrix(np.stack([c.R for c in cams]))
    if len(cams) == 2:
        R = Slerp([0.0, 1.0], rotations)([w[1]]).as_matrix()[0]
    else:
        R = rotations.mean(weights=w).as_matrix()
    return Camera(name=name, width=cams[0].width, height=cams[0].height, K=K, R=R, t=-R @ centre, dist=dist)


# The strengths of `weights_for_centre`'s terms (dimensionless: lengths in units of the array's extent).
SUM_WEIGHT = 1e3  # the sum of the weights is 1, before the blended centre is nearest the eye
CONSTRAINT_WEIGHT = 1e4  # the weights make the nearest point, before they are local and even
SPREAD = 1e-3  # the evenness term Σ w², against the locality term Σ w_p ‖c_p − x‖²


def _extent(C: np.ndarray) -> float:
    """The array's extent L: its largest distance between two camera centres (m), at least 1 mm."""
    return max(float(np.sqrt(np.max(np.sum((C[:, None, :] - C[None, :, :]) ** 2, axis=2)))), 1e-3)


def nearest_blend_system(centres: np.ndarray, eye: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Step 1 of `weights_for_centre`: min ‖A w − b‖, w ≥ 0, whose solution's blended centre
    is the point of the cameras' convex hull nearest the eye (unique, though the weights
    need not be).

    Rows: the sum of the weights is 1 (one row, times `SUM_WEIGHT`); Σ w_p (c_p − eye) / L
    is 0 (three rows; L the array's extent).

    Args:
        centres: (p,3) camera centres (m). eye: (3,) the eye (m).

    Returns:
        A (4,p) and b (4,) float64.
    """
    C = np.asarray(centres, np.float64)
    eye = np.asarray(eye, np.float64).reshape(3)
    A = np.vstack([np.full((1, len(C)), SUM_WEIGHT), ((C - eye) / _extent(C)).T])
    return A, np.array([SUM_WEIGHT, 0.0, 0.0, 0.0])


def centre_weights_system(centres: np.ndarray, point: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Step 2 of `weights_for_centre`: min ‖A w − b‖, w ≥ 0, for a point that a blend of the
    cameras reaches (step 1's): among the weights whose blended centre is the point, those
    on the cameras nearest it, Σ w_p ‖c_p − x‖² / L² (the Delaunay interpolant of the
    camera centres: on a 2x2 array a corner's two neighbours, not the opposite corners), and
    the most even of them, `SPREAD` Σ w_p² (which makes the answer unique: equal weights at
    the centre of a square).

    Rows: the sum is 1 and Σ w_p (c_p − x) / L is 0 (four rows, times `CONSTRAINT_WEIGHT`);
    then √SPREAD · I w = −‖c_p − x‖² / (2 L² √SPREAD) (p rows), which together are the two
    terms above up to a constant.

    Args:
        centres: (p,3) camera centres (m). point: (3,) the point (m).

    Returns:
        A (4+p, p) and b (4+p,) float64. The viewer's script builds the same rows
        (mvtex/web/viewmath.js, checked against this function by the tests).
    """
    C = np.asarray(centres, np.float64)
    x = np.asarray(point, np.float64).reshape(3)
    L = _extent(C)
    p = len(C)
    near = np.sum((C - x) ** 2, axis=1) / L ** 2
    A = np.vstack([np.full((1, p), CONSTRAINT_WEIGHT), CONSTRAINT_WEIGHT * ((C - x) / L).T, np.sqrt(SPREAD) * np.eye(p)])
    b = np.concatenate([[CONSTRAINT_WEIGHT, 0.0, 0.0, 0.0], -near / (2.0 * np.sqrt(SPREAD))])
    return A, b


def weights_for_centre(rig: Rig, names: Sequence[str], centre: np.ndarray) -> dict[str, float]:
    """Weights ≥ 0 summing to 1 over cameras `names` whose blended centre is nearest `centre`;
    where several do (inside the array's span), those on the cameras nearest it, the most
    even of them. Two non-negative least-squares problems (`nearest_blend_system`, then
    `centre_weights_system` at the nearest point).

    A camera's own centre gives it weight 1 (every camera of the built-in rigs is a corner of
    the array's hull); the midpoint of two neighbours gives them 0.5 each, the centre of a
    2x2 square 0.25 each.
    """

    C = np.stack([rig[n].center for n in names])
    limit = 50 * len(names) + 100
    w, _ = nnls(*nearest_blend_system(C, centre), maxiter=limit)
    nearest = (w / w.sum()) @ C
    w, _ = nnls(*centre_weights_system(C, nearest), maxiter=limit)
    w = w / w.sum()
    return {n: float(x) for n, x in zip(names, w)}
