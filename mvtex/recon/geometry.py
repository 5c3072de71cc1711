"""Multi-view geometry of points seen by calibrated pinhole cameras (NumPy only, no GL).

Cameras follow `mvtex.data.camera` (OpenCV): x_cam = R X + t, pixel = K (x/z, y/z, 1), with
skew K[0,1] honoured everywhere. All functions are vectorised over N points observed by
the same C cameras:

    pixels  (N,C,2) float64  OpenCV pixels; anything (NaN included) where the weight is 0
    weights (N,C)   float64  1 where camera c observes point n, 0 where not (real weights
                             scale that camera's rows / residuals)

Inputs with a wrong shape raise ValueError naming the argument, the expected shape and
the shape received. An observation counts only where its weight is > 0 *and* its pixel is
finite; a point needs 2 such observations whose rays meet at an angle of at least
MIN_TRIANGULATION_ANGLE_DEG (cameras at one centre, or almost one, see no depth), else
it is NaN ("no point").

    triangulate_dlt       linear DLT in normalised coordinates
    refine_points         Gauss-Newton on the summed squared reprojection error
    triangulate_points    both (what `mvtex triangulate --engine mvtex` runs per track)
    triangulation_angles  the widest angle between the rays that observe each point
    project_points        all points into all cameras
    in_image              which pixels fall inside an image
    reprojection_errors   (N,C) pixel distances
    least_disagreement    which of several observation combinations agrees best
    surface_distance      distance from points to a triangle mesh
    rmse                  root mean square distance between two point sets
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy.spatial import cKDTree

from mvtex.data.camera import Camera, _as_float_array, image_contains
from mvtex.data.mesh import rms_distance
from mvtex.util.checks import as_list, check_shape
from mvtex.util.errors import OptionError

MIN_TRIANGULATION_ANGLE_DEG = 1.0
"""Points whose observing rays all meet within this angle (degrees) are not triangulated:
their depth is set by pixel noise (at 1°, 0.1 px of error on a 1000 px focal length moves
a point 2 m away by ~1 cm). COLMAP's default (`min_tri_angle`) is 1.5°."""


def camera_arrays(cameras: Sequence[Camera]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stacked intrinsics K (C,3,3), rotations R (C,3,3) and translations t (C,3), float64."""
    cameras = _cameras(cameras)
    if len(cameras) == 0:
        raise OptionError("cameras", "must hold at least one camera, got 0")
    return (np.stack([c.K for c in cameras]), np.stack([c.R for c in cameras]), np.stack([c.t for c in cameras]))


def _cameras(cameras) -> list[Camera]:
    """The cameras argument as a list of Camera (a Rig will do); OptionError otherwise."""

    return as_list(cameras, "cameras", Camera, "Camera (or a Rig)")


def _project(K: np.ndarray, R: np.ndarray, t: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points (N,3) into C cameras: pixels (N,C,2) and camera coordinates (N,C,3)."""
    y = np.einsum("cij,nj->nci", R, points) + t[None]
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = y[..., :2] / y[..., 2:3]
    pix = np.stack([K[:, 0, 0] * xy[..., 0] + K[:, 0, 1] * xy[..., 1] + K[:, 0, 2],
                    K[:, 1, 1] * xy[..., 1] + K[:, 1, 2]], axis=-1)
    return pix, y


def project_points(cameras: Sequence[Camera], points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project every point into every camera (`Camera.project` for C cameras at once).

    Args:
        cameras: the C cameras.
        points: (N,3) world points.

    Returns:
        pixels (N,C,2) float64 (NaN/inf where z = 0) and camera coordinates (N,C,3) float64
        (z = [..., 2] is the depth; ≤ 0 behind the camera).
    """
    arrays = camera_arrays(cameras)
    points = _as_array(points, "points")
    check_shape(points, "points", ("N", 3))
    return _project(*arrays, points)


def in_image(pixels: np.ndarray, width: int, height: int) -> np.ndarray:
    """Which OpenCV pixel positions (..., 2) lie on a width x height image, (...) bool.

    Pixel centres are integers, so the image spans (-0.5, width - 0.5) x (-0.5, height - 0.5);
    NaN is outside.
    """
    pixels = np.asarray(pixels)
    if pixels.shape[-1:] != (2,):
        raise ValueError(f"pixels must have shape (...,2), got {pixels.shape}")
    return image_contains(pixels, width, height)


def reprojection_errors(cameras: Sequence[Camera], points: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Pixel distance (N,C) float64 between the projections of points (N,3) and pixels (N,C,2)."""
    points = np.asarray(points, dtype=np.float64)
    sizes = check_shape(points, "points", ("N", 3))
    check_shape(pixels, "pixels", ("N", len(cameras), 2), sizes)
    pix, _ = _project(*camera_arrays(cameras), points)
    return np.linalg.norm(pix - pixels, axis=-1)


def _check_observations(cameras: Sequence[Camera], pixels: np.ndarray, weights: np.ndarray) -> dict[str, int]:
    cameras = _cameras(cameras)
    sizes = check_shape(pixels, "pixels", ("N", len(cameras), 2))
    return check_shape(weights, "weights", ("N", len(cameras)), sizes)


def observed(pixels: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(N,C) float64 weights of the observations that count: the weight where it is > 0
    and the pixel (N,C,2) finite, else 0.

    Raises:
        OptionError: a weight that is negative or not finite.
    """
    w = np.array(weights, dtype=np.float64)
    if not np.all(np.isfinite(w)) or np.any(w < 0):
        raise OptionError("weights", "must be finite and ≥ 0 (0 where a camera does not observe the point)")
    finite = np.all(np.isfinite(np.asarray(pixels, dtype=np.float64)), axis=-1)
    return np.where(finite & (w > 0), w, 0.0)


TRIANGULATION_BLOCK = 1 << 18
"""Observations (points × cameras) `triangulate_points` works on at a time, and camera pairs
(points × cameras²) `triangulation_angles` compares at a time: memory stays that of a block
whatever the number of cameras."""


def triangulation_angles(cameras: Sequence[Camera], points: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """The widest angle (degrees) between two rays that observe each point.

    Args:
        cameras: the C cameras.
        points: (N,3) world points.
        weights: (N,C) > 0 where camera c observes point n.

    Returns:
        (N,) float64 degrees: 0 where the observing cameras share one centre, NaN where the
        point is not finite or fewer than 2 cameras observe it.
    """
    points = np.asarray(points, dtype=np.float64)
    sizes = check_shape(points, "points", ("N", 3))
    check_shape(weights, "weights", ("N", len(cameras)), sizes)
    centers = np.stack([c.center for c in cameras])  # (C,3)
    seen = np.asarray(weights) > 0
    smallest = np.full(len(points), np.inf)
    # In blocks of points: every pair of cameras is compared, (block,C,C) at a time.
    block = max(1, TRIANGULATION_BLOCK // max(1, len(cameras) ** 2))
    for start in range(0, len(points), block):
        rows = slice(start, start + block)
        rays = points[rows, None, :] - centers[None]  # (b,C,3)
        with np.errstate(invalid="ignore", divide="ignore"):
            rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
        cos = np.einsum("nci,ndi->ncd", rays, rays)
        pair = seen[rows, :, None] & seen[rows, None, :]
        smallest[rows] = np.where(pair & np.isfinite(cos), cos, np.inf).min(axis=(1, 2), initial=np.inf)
    with np.errstate(invalid="ignore"):
        angle = np.degrees(np.arccos(np.clip(smallest, -1.0, 1.0)))
    enough = (seen.sum(axis=1) >= 2) & np.all(np.isfinite(points), axis=1) & np.isfinite(smallest)
    return np.where(enough, angle, np.nan)


def triangulate_dlt(cameras: Sequence[Camera], pixels: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Linear multi-view triangulation (DLT), vectorised over points.

    Rows are built in normalised camera coordinates (K⁻¹ x) for conditioning; each row is
    scaled by its observation's weight.

    Args:
        cameras: the C cameras.
        pixels: (N,C,2) OpenCV pixel observations.
        weights: (N,C) weights; ≥ 2 non-zero per point.

    Returns:
        (N,3) float64 points (NaN where degenerate or fewer than 2 observations count:
        weight > 0 and a finite pixel).
    """
    _check_observations(cameras, pixels, weights)
    weights = observed(pixels, weights)
    K, R, t = camera_arrays(cameras)
    P = np.concatenate([R, t[:, :, None]], axis=2)  # (C,3,4) cam_from_world
    pix = np.nan_to_num(np.asarray(pixels, dtype=np.float64))
    xn = (pix - K[None, :, :2, 2]) / np.stack([K[:, 0, 0], K[:, 1, 1]], 1)[None]
    xn[..., 0] -= xn[..., 1] * (K[None, :, 0, 1] / K[None, :, 0, 0])  # skew, usually 0
    rows_x = xn[..., 0:1] * P[None, :, 2] - P[None, :, 0]
    rows_y = xn[..., 1:2] * P[None, :, 2] - P[None, :, 1]
    A = np.concatenate([rows_x, rows_y], axis=1) * np.concatenate([weights, weights], axis=1)[..., None]
    _, _, vt = np.linalg.svd(A, full_matrices=False)  # (N,4,4): never U's (N,2C,2C)
    X = vt[:, -1]
    with np.errstate(divide="ignore", invalid="ignore"):
        out = X[:, :3] / X[:, 3:4]
    out[~np.all(np.isfinite(out), axis=1) | ((weights > 0).sum(axis=1) < 2)] = np.nan
    return out


def projection_jacobian(K: np.ndarray, R: np.ndarray, camera_points: np.ndarray) -> np.ndarray:
    """d(pixel)/d(world point) of the pinhole projection, skew included.

    With y = R X + t, (a, b) = (y0/z, y1/z): u = fx a + s b + cx, v = fy b + cy and
    da/dX = (R_0 - a R_2) / z, db/dX = (R_1 - b R_2) / z.

    Args:
        K: (C,3,3) intrinsics; R: (C,3,3) rotations.
        camera_points: (N,C,3) camera coordinates y of the points.

    Returns:
        (N,C,2,3) float64 (NaN/inf where z = 0).
    """
    z = camera_points[..., 2][..., None]
    with np.errstate(divide="ignore", invalid="ignore"):
        a_num = R[None, :, 0] - (camera_points[..., 0:1] / z) * R[None, :, 2]  # z * da/dX
        b_num = R[None, :, 1] - (camera_points[..., 1:2] / z) * R[None, :, 2]  # z * db/dX
        du = (K[None, :, 0, 0, None] * a_num + K[None, :, 0, 1, None] * b_num) / z
        dv = K[None, :, 1, 1, None] * b_num / z
    return np.stack([du, dv], axis=2)


def refine_points(cameras: Sequence[Camera], points: np.ndarray, pixels: np.ndarray, weights: np.ndarray,
                  iterations: int = 5) -> np.ndarray:
    """Gauss-Newton on the summed squared (weighted) reprojection error, vectorised over points.

    Args:
        cameras: the C cameras.
        points: (N,3) initial points.
        pixels: (N,C,2) OpenCV pixel observations.
        weights: (N,C) weights (0 where not observed).
        iterations: at most this many steps; a step that does not lower a point's error
            is not taken, and the loop ends when no point improves.

    Returns:
        (N,3) float64 refined points.
    """
    sizes = _check_observations(cameras, pixels, weights)
    check_shape(points, "points", ("N", 3), sizes)
    K, R, t = camera_arrays(cameras)
    X = np.array(points, dtype=np.float64)
    w = observed(pixels, weights)
    pixels = np.nan_to_num(np.asarray(pixels, dtype=np.float64))

    def cost(X):
        with np.errstate(invalid="ignore", over="ignore"):
            pix, y = _project(K, R, t, X)
            r = np.nan_to_num(pix - pixels, nan=1e6) * w[..., None]
            return np.sum(r ** 2, axis=(1, 2)), pix, y

    c0, pix, y = cost(X)
    for _ in range(iterations):
        r = (pix - pixels) * w[..., None]  # (N,C,2)
        J = np.nan_to_num(projection_jacobian(K, R, y) * w[..., None, None])  # (N,C,2,3)
        JtJ = np.einsum("ncki,nckj->nij", J, J) + 1e-12 * np.eye(3)
        Jtr = np.einsum("ncki,nck->ni", J, np.nan_to_num(r))
        try:
            delta = -np.linalg.solve(JtJ, Jtr[..., None])[..., 0]
        except np.linalg.LinAlgError:
            delta = -np.stack([np.linalg.lstsq(a, b, rcond=None)[0] for a, b in zip(JtJ, Jtr)])
        X_new = X + delta
        c1, pix1, y1 = cost(X_new)
        better = np.isfinite(c1) & (c1 < c0)
        X[better], c0[better] = X_new[better], c1[better]
        pix[better], y[better] = pix1[better], y1[better]
        if not better.any():
            break
    return X


def triangulate_points(cameras: Sequence[Camera], pixels: np.ndarray, weights: np.ndarray,
                       iterations: int = 5, min_angle_deg: float = MIN_TRIANGULATION_ANGLE_DEG) -> np.ndarray:
    """DLT, then Gauss-Newton from it where the DLT is not degenerate.

    Args and shapes as `triangulate_dlt`; iterations as `refine_points`.
        min_angle_deg: a point whose observing rays all meet within this angle is NaN
            (`triangulation_angles`; 0 keeps every point that is not degenerate).

    Returns:
        (N,3) float64 points: NaN where degenerate, where fewer than 2 observations count
        (weight > 0 and a finite pixel), or where the rays meet at less than min_angle_deg.

    Raises:
        ValueError: shapes that do not fit (naming the argument); OptionError: weights
            negative or not finite, iterations or min_angle_deg out of range.
    """
    if isinstance(iterations, bool) or not isinstance(iterations, (int, np.integer)) or not 0 <= iterations <= 100:
        raise OptionError("iterations", f"must be an integer in 0..100, got {iterations!r}")
    if isinstance(min_angle_deg, bool) or not isinstance(min_angle_deg, (int, float, np.floating)) \
            or not 0 <= min_angle_deg < 180:
        raise OptionError("min_angle_deg", f"must be a number in [0, 180), got {min_angle_deg!r}")
    cameras = _cameras(cameras)
    pixels = _as_array(pixels, "pixels")
    weights = _as_array(weights, "weights")
    _check_observations(cameras, pixels, weights)
    # In blocks of points: the DLT rows and the Jacobians take ~100 bytes per observation,
    # so memory stays that of a block whatever the number of cameras.
    block = max(1, TRIANGULATION_BLOCK // max(1, len(cameras)))
    X = np.full((len(pixels), 3), np.nan)
    for start in range(0, len(pixels), block):
        rows = slice(start, start + block)
        X[rows] = _triangulate_block(cameras, pixels[rows], weights[rows], iterations, min_angle_deg)
    return X


def _triangulate_block(cameras, pixels: np.ndarray, weights: np.ndarray, iterations: int,
                       min_angle_deg: float) -> np.ndarray:
    X = triangulate_dlt(cameras, pixels, weights)
    weights = observed(pixels, weights)
    good = np.all(np.isfinite(X), axis=1)
    if good.any():
        X[good] = refine_points(cameras, X[good], pixels[good], weights[good], iterations)
    if min_angle_deg > 0 and len(X):
        narrow = ~(triangulation_angles(cameras, X, weights) >= min_angle_deg)
        X[narrow] = np.nan
    return X


def _as_array(value, name: str) -> np.ndarray:
    """`value` as a float64 array; OptionError naming `name` when it is not numbers."""

    return _as_float_array(value, name)


def least_disagreement(cameras: Sequence[Camera], pixels: np.ndarray) -> tuple[int, np.ndarray]:
    """Of k candidate observation sets of one point, the one whose rays agree best.

    Each candidate (one pixel per camera) is triangulated (DLT); the one with the least
    summed squared reprojection error wins.

    Args:
        cameras: the C cameras (all observe every candidate).
        pixels: (k,C,2) the candidates.

    Returns:
        (index of the best candidate, its DLT point (3,)); (-1, NaN point) when every
        candidate is degenerate.
    """
    check_shape(pixels, "pixels", ("k", len(cameras), 2))
    X = triangulate_dlt(cameras, pixels, np.ones(pixels.shape[:2]))
    err = reprojection_errors(cameras, np.nan_to_num(X), pixels)
    cost = np.where(np.all(np.isfinite(X), axis=1), np.sum(err ** 2, axis=1), np.inf)
    if not len(cost) or not np.isfinite(cost.min()):
        return -1, np.full(3, np.nan)
    best = int(np.argmin(cost))
    return best, X[best]


def surface_distance(points: np.ndarray, positions: np.ndarray, faces: np.ndarray, k: int = 8) -> np.ndarray:
    """Distance from points to a triangle mesh, over the triangles around the k nearest vertices.

    Exact wherever the closest triangle has a vertex among the k nearest (always on the
    dense meshes this is used for; farther points get an upper bound).

    Args:
        points: (N,3) query points.
        positions: (n,3) mesh vertices; faces: (m,3) int triangles.
        k: nearest vertices whose triangles are searched.

    Returns:
        (N,) float64 distances.
    """
    import trimesh.triangles  # noqa: PLC0415 (loaded on use)

    points = np.asarray(points, dtype=np.float64)
    check_shape(points, "points", ("N", 3))
    check_shape(positions, "positions", ("n", 3))
    check_shape(faces, "faces", ("m", 3))
    if len(points) == 0:
        return np.zeros(0)
    n = len(positions)
    faces = np.asarray(faces, dtype=np.int64)
    k = min(k, n)
    _, near = cKDTree(positions).query(points, k=k)
    near = np.asarray(near).reshape(len(points), k)
    # vertex -> incident faces, padded with -1.
    order = np.argsort(faces.ravel(), kind="stable")
    vert = faces.ravel()[order]
    face_of = order // 3
    counts = np.bincount(vert, minlength=n)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    width = int(counts.max())
    table = np.full((n, width), -1, dtype=np.int64)
    slot = np.arange(len(vert)) - start[vert]
    table[vert, slot] = face_of
    cand = table[near].reshape(len(points), -1)
    pi, ci = np.nonzero(cand >= 0)
    tris = positions[faces[cand[pi, ci]]]
    closest = trimesh.triangles.closest_point(tris, points[pi])
    d = np.linalg.norm(closest - points[pi], axis=1)
    out = np.full(len(points), np.inf)
    np.minimum.at(out, pi, d)
    return out


def rmse(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float | None:
    """Root mean square Euclidean distance between corresponding points.

    Args:
        a, b: (..., n, 3) point sets of the same shape (e.g. (n,3) or (K,n,3) poses).
        mask: optional (n,) bool: only these points count.

    Returns:
        The RMSE, or None when no point counts.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape or a.ndim < 2:
        raise ValueError(f"a and b must have one shape (..., n, 3), got {a.shape} and {b.shape}")
    return rms_distance(a, b, mask)
