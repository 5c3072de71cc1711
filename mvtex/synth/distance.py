"""Signed distances from cloth to its body, pose after pose (the clearance statistics of
`mvtex.synth.generate`).

Cloth and body move together, so the body vertices near a cloth vertex are found once,
at rest; in each pose a compiled loop (numba; cached on disk like `mvtex.sliding.kernels`)
picks the few of them nearest to the vertex now and measures the exact point-to-triangle
distance to the triangles around those. The sign is that of the offset from the closest point along
the closest triangle's outward normal: negative inside the body.
"""

from __future__ import annotations

import numpy as np
from numba import prange
from scipy.spatial import cKDTree

from mvtex.data.mesh import vertex_normals
from mvtex.util.compiled import compiled as _compiled


@_compiled
def _closest(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz):
    """Barycentric coordinates (v, w) of the point of triangle abc closest to p (Ericson,
    Real-Time Collision Detection 5.1.5): the point is a + v (b - a) + w (c - a). In
    scalars: no small arrays in the loop."""
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:
        return 0.0, 0.0
    bpx, bpy, bpz = px - bx, py - by, pz - bz
    d3 = abx * bpx + aby * bpy + abz * bpz
    d4 = acx * bpx + acy * bpy + acz * bpz
    if d3 >= 0.0 and d4 <= d3:
        return 1.0, 0.0
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        return d1 / (d1 - d3), 0.0
    cpx, cpy, cpz = px - cx, py - cy, pz - cz
    d5 = abx * cpx + aby * cpy + abz * cpz
    d6 = acx * cpx + acy * cpy + acz * cpz
    if d6 >= 0.0 and d5 <= d6:
        return 0.0, 1.0
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        return 0.0, d2 / (d2 - d6)
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return 1.0 - w, w
    denom = 1.0 / (va + vb + vc)
    return vb * denom, vc * denom


@_compiled
def _signed_range(points, vertices, normals, faces, near, incident, nearest, start, stop, out):
    """Signed distance of points start:stop to the faces around the `nearest` of their
    candidate vertices `near` that are nearest to them now; the sign: of the offset from the
    closest point along the vertex normals interpolated there (robust where the closest
    point is a corner or an edge, whose faces' own normals may disagree)."""
    pick = np.empty(nearest, np.int64)
    pick_sq = np.empty(nearest)
    tested = np.empty(nearest * incident.shape[1], np.int64)
    for i in range(start, stop):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        for k in range(nearest):
            pick_sq[k] = np.inf
            pick[k] = -1
        for j in range(near.shape[1]):  # insertion into the short list of the nearest vertices
            v = near[i, j]
            ex, ey, ez = px - vertices[v, 0], py - vertices[v, 1], pz - vertices[v, 2]
            sq = ex * ex + ey * ey + ez * ez
            k = nearest - 1
            if sq >= pick_sq[k]:
                continue
            while k > 0 and pick_sq[k - 1] > sq:
                pick_sq[k], pick[k] = pick_sq[k - 1], pick[k - 1]
                k -= 1
            pick_sq[k], pick[k] = sq, v
        best_sq = np.inf
        sign = 1.0
        count = 0
        for k in range(nearest):
            for j in range(incident.shape[1]):
                f = incident[pick[k], j]
                if f < 0:
                    break
                seen = False
                for t in range(count):  # the picked vertices share faces: test each once
                    if tested[t] == f:
                        seen = True
                        break
                if seen:
                    continue
                tested[count] = f
                count += 1
                ia, ib, ic = faces[f, 0], faces[f, 1], faces[f, 2]
                ax, ay, az = vertices[ia, 0], vertices[ia, 1], vertices[ia, 2]
                bx, by, bz = vertices[ib, 0], vertices[ib, 1], vertices[ib, 2]
                cx, cy, cz = vertices[ic, 0], vertices[ic, 1], vertices[ic, 2]
                v, w = _closest(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz)
                u = 1.0 - v - w
                dx = px - (u * ax + v * bx + w * cx)
                dy = py - (u * ay + v * by + w * cy)
                dz = pz - (u * az + v * bz + w * cz)
                dist_sq = dx * dx + dy * dy + dz * dz
                if dist_sq < best_sq:
                    best_sq = dist_sq
                    nx = u * normals[ia, 0] + v * normals[ib, 0] + w * normals[ic, 0]
                    ny = u * normals[ia, 1] + v * normals[ib, 1] + w * normals[ic, 1]
                    nz = u * normals[ia, 2] + v * normals[ib, 2] + w * normals[ic, 2]
                    sign = 1.0 if dx * nx + dy * ny + dz * nz >= 0.0 else -1.0
        out[i] = sign * np.sqrt(best_sq)


def _signed_parallel(points, vertices, normals, faces, near, incident, nearest, out):
    """`_signed_range` over all points, in blocks on the cores (each point independent)."""
    blocks = 32
    n = points.shape[0]
    for b in prange(blocks):
        _signed_range(points, vertices, normals, faces, near, incident, nearest, b * n // blocks,
                      (b + 1) * n // blocks, out)


_signed_distances = _compiled(_signed_parallel, parallel=True)


class SurfaceDistance:
    """Signed distance from points that move with a body to the body's surface.

    Args:
        rest_points: (n,3) the points at rest (cloth vertices).
        body_rest: (nb,3) the body's vertices at rest; body_faces: (mb,3) int, outward.
        neighbours: how many nearest body vertices at rest are a point's candidates.
        nearest: of these, around how many of the nearest in a pose the faces are measured.
    """

    def __init__(self, rest_points: np.ndarray, body_rest: np.ndarray, body_faces: np.ndarray, neighbours: int = 12,
                 nearest: int = 4):

        self.faces = np.ascontiguousarray(body_faces, dtype=np.int64)
        self.nearest = nearest
        _, near = cKDTree(np.asarray(body_rest, np.float64)).query(np.asarray(rest_points, np.float64), k=neighbours)
        self.near = np.ascontiguousarray(near, dtype=np.int64)
        count = np.bincount(self.faces.ravel(), minlength=len(body_rest))
        order = np.argsort(self.faces.ravel(), kind="stable")
        starts = np.concatenate([[0], np.cumsum(count)])
        self.incident = np.full((len(body_rest), count.max()), -1, np.int64)
        for j in range(count.max()):
            has = count > j
            self.incident[has, j] = order[starts[:-1][has] + j] // 3

    def __call__(self, points: np.ndarray, body_positions: np.ndarray) -> np.ndarray:
        """(n,) float64 signed distances (m) of points (n,3) to the body in positions (nb,3)."""

        body = np.ascontiguousarray(body_positions, np.float64)
        out = np.empty(len(points))
        _signed_distances(np.ascontiguousarray(points, np.float64), body, vertex_normals(body, self.faces), self.faces,
                          self.near, self.incident, self.nearest, out)
        return out
