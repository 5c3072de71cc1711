"""Mannequins as implicit surfaces: smooth unions of round cones, ellipsoids and elliptic
stacks (signed-distance-like functions, negative inside), meshed once at rest by marching
cubes (`mesh_implicit`) and posed by blending per-segment transforms (in `synth.shirt` and
`synth.skirt`, by the same warp as the garment they wear).
"""

from __future__ import annotations

import numpy as np


def smooth_min(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum (a union of two implicit solids, blended over about k)."""
    h = np.maximum(k - np.abs(a - b), 0.0) / k
    return np.minimum(a, b) - h * h * k * 0.25


def smooth_max(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth maximum (an intersection, rounded over about k)."""
    return -smooth_min(-a, -b, k)


def round_cone(points: np.ndarray, start, end, start_radius: float, end_radius: float) -> np.ndarray:
    """(n,) implicit of a capsule from `start` to `end` whose radius varies linearly."""
    start, end = np.asarray(start, np.float64), np.asarray(end, np.float64)
    axis = end - start
    t = np.clip(((points - start) @ axis) / (axis @ axis), 0.0, 1.0)
    radius = start_radius + (end_radius - start_radius) * t
    return np.linalg.norm(points - (start + t[:, None] * axis), axis=1) - radius


def ellipsoid(points: np.ndarray, centre, radii) -> np.ndarray:
    """(n,) implicit of an axis-aligned ellipsoid (the usual first-order distance bound)."""
    radii = np.asarray(radii, np.float64)
    q = (points - np.asarray(centre, np.float64)) / radii
    k0 = np.linalg.norm(q, axis=1)
    k1 = np.linalg.norm(q / radii, axis=1)
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-12)


def elliptic_stack(points: np.ndarray, profile: np.ndarray, rounding: float) -> np.ndarray:
    """(n,) implicit of a vertical solid whose horizontal sections are ellipses.

    Args:
        profile: (k,3) rows (y, semi-axis along x, semi-axis along z), y increasing; the
            solid spans profile[0, 0] <= y <= profile[-1, 0], its ends rounded.
        rounding: radius of the rounding of the two ends (m).
    """
    y = points[:, 1]
    ax = np.interp(y, profile[:, 0], profile[:, 1])
    bz = np.interp(y, profile[:, 0], profile[:, 2])
    side = (np.hypot(points[:, 0] / ax, points[:, 2] / bz) - 1.0) * np.minimum(ax, bz)
    ends = np.maximum(y - profile[-1, 0], profile[0, 0] - y)
    return smooth_max(side, ends, rounding)


def mesh_implicit(function, lo, hi, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """The zero level set of an implicit function as a closed triangle mesh (marching
    cubes, scikit-image), faces counter-clockwise seen from outside.

    Args:
        function: (n,3) points -> (n,) values, negative inside.
        lo, hi: corners of the box sampled (the solid must lie strictly inside it).
        spacing: grid step (m).

    Returns:
        vertices (v,3) float64 and faces (f,3) int32.
    """
    from skimage.measure import marching_cubes  # noqa: PLC0415 (loaded on use)

    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    counts = np.ceil((hi - lo) / spacing).astype(int) + 1
    axes = [lo[i] + spacing * np.arange(counts[i]) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    volume = function(grid).reshape(tuple(counts))
    vertices, faces, _, _ = marching_cubes(volume, 0.0, spacing=(spacing,) * 3)
    vertices = vertices.astype(np.float64) + lo
    corners = vertices[faces]
    signed_volume = np.einsum("ij,ij->i", corners[:, 0], np.cross(corners[:, 1], corners[:, 2])).sum()
    if signed_volume < 0:  # the solid is where the function is negative: make normals point out of it
        faces = faces[:, ::-1]
    return vertices, np.ascontiguousarray(faces, dtype=np.int32)
