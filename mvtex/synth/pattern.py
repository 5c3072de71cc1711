"""Flat garment patterns meshed: a closed boundary polygon in pattern coordinates (meters of
material) becomes a triangle mesh of near-equilateral triangles (`mesh_pattern`).

Pieces that are sewn together share the samples of their seams: `sample_curve` places
samples at the same arc lengths on both, so the seam vertices of two pieces name the same
material points.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import Delaunay


def sample_curve(points: np.ndarray, spacing: float, include_end: bool = False) -> np.ndarray:
    """Samples of a polyline at equal arc-length steps of about `spacing`.

    Args:
        points: (k,2) polyline vertices (k >= 2), a finely sampled curve.
        spacing: target distance between samples.
        include_end: also return the last point (else the samples stop one step before it,
            so that consecutive curves of a closed loop can be concatenated).

    Returns:
        (s,2) float64 samples, the first at points[0].
    """
    points = np.asarray(points, dtype=np.float64)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    count = max(1, int(round(arc[-1] / spacing)))
    at = np.linspace(0.0, arc[-1], count + 1)
    if not include_end:
        at = at[:-1]
    return np.stack([np.interp(at, arc, points[:, 0]), np.interp(at, arc, points[:, 1])], axis=1)


def _segment_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N,) distance of points (N,2) to the nearest of the segments a[i]-b[i] ((M,2) each)."""
    ab = b - a
    t = np.einsum("nmk,mk->nm", points[:, None, :] - a[None], ab) / np.maximum(np.einsum("mk,mk->m", ab, ab), 1e-300)
    closest = a[None] + np.clip(t, 0.0, 1.0)[..., None] * ab[None]
    return np.linalg.norm(points[:, None, :] - closest, axis=2).min(axis=1)


def mesh_pattern(boundary: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate the inside of a simple polygon with near-equilateral triangles.

    Interior points lie on a triangular lattice of the given spacing (those closer than
    0.55 spacing to the boundary dropped); with boundary samples at most `spacing` apart,
    every boundary edge is a Delaunay edge (its diametral circle holds no other point), so
    the Delaunay triangulation, restricted to the inside, has the boundary as its border.

    Args:
        boundary: (b,2) the polygon's vertices, counter-clockwise, not repeating the first.
        spacing: edge length of the lattice.

    Returns:
        points (p,2) float64 (the boundary first, in its order) and faces (f,3) int32,
        counter-clockwise.

    Raises:
        RuntimeError: a boundary edge is missing from the triangulation (samples too sparse).
    """
    from matplotlib.path import Path as PolygonPath  # noqa: PLC0415 (loaded on use)

    boundary = np.asarray(boundary, dtype=np.float64)
    polygon = PolygonPath(np.vstack([boundary, boundary[:1]]), closed=True)
    lo, hi = boundary.min(axis=0), boundary.max(axis=0)
    row_step = spacing * np.sqrt(3.0) / 2.0
    rows = []
    for r, y in enumerate(np.arange(lo[1] + 0.5 * row_step, hi[1], row_step)):
        x = np.arange(lo[0] + (0.5 * spacing if r % 2 else 0.0), hi[0], spacing)  # every other row shifted
        rows.append(np.stack([x, np.full(len(x), y)], axis=1))
    lattice = np.concatenate(rows)
    lattice = lattice[polygon.contains_points(lattice)]
    ends = np.roll(boundary, -1, axis=0)
    lattice = lattice[_segment_distance(lattice, boundary, ends) > 0.55 * spacing]
    points = np.concatenate([boundary, lattice])
    triangles = Delaunay(points).simplices
    centroids = points[triangles].mean(axis=1)
    faces = triangles[polygon.contains_points(centroids)]
    p = points[faces]
    area = (p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1]) - (p[:, 1, 1] - p[:, 0, 1]) * (p[:, 2, 0] - p[:, 0, 0])
    faces = np.where((area < 0)[:, None], faces[:, [0, 2, 1]], faces)
    edges = {tuple(sorted(e)) for f in faces for e in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0]))}
    count = len(boundary)
    missing = [i for i in range(count) if tuple(sorted((i, (i + 1) % count))) not in edges]
    if missing:
        raise RuntimeError(f"pattern boundary edges {missing[:5]} are not in the triangulation")
    return points, faces.astype(np.int32)
