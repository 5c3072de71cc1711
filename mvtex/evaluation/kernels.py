"""Compiled kernels of the evaluation (`mvtex.evaluation.evaluate`, `MaterialMap`).

Per pixel the evaluation does a handful of multiply-adds (uv and rest points interpolated
from barycentrics, two distances, a chart comparison); written with NumPy it gathers and
keeps a dozen (pixels, 3, C) temporaries per image. In one compiled pass over the pixels
(numba, as `mvtex.sliding.kernels`) it writes only what it returns.

- `pixel_errors`: the pixels where both renders show cloth, their uv and material errors
  of the baseline, the texcoords' uv per pixel (for the material map), chart agreement,
  and the pixel counts of the body share.
- `locate`: `MaterialMap`'s lookup of uv points in the layout's triangles (the texel's
  triangle, else the 3x3 texels', else the triangles around the best candidate).
"""

from __future__ import annotations

import numpy as np

from mvtex.util.compiled import compiled as _compiled


@_compiled
def pixel_errors(base_tri, base_bary, sub_tri, sub_bary, num_faces, num_sub_faces, faces, uv, rest, sub_faces,
                 sub_uv, sub_rest, texcoords, face_chart, sub_face_chart):
    """One image's per-pixel values over the box of a pair raster.

    Args:
        base_tri, sub_tri: (P,) int32 ids of gt (base faces) and of the set's mesh (ids
            from num_faces, resp. num_sub_faces, on are the body's; -1 background).
        base_bary, sub_bary: (P,3) float32 barycentrics.
        faces (m,3) int64, uv (n,2) float32, rest (n,3) float64: the gt mesh (rest may be
        (0,3): no material error). sub_faces (m',3) int64, sub_uv (n',2) float32 (T_G),
        sub_rest (n',3) float64, texcoords (n',2) float32: the set's mesh.
        face_chart (m,), sub_face_chart (m',) int64: the chart of each face.

    Returns:
        pixels (k,) int64 where both show cloth; e_b, e_t (k,) float64 uv errors of the
        baseline and the texcoords; uv_t (k,2) float64 (float32 values) the texcoords' uv;
        other (k,) bool different charts; points_g (k,3) float64 the gt material points;
        mat_b (k,) float64 the baseline's material error (0 without rest); and
        (hidden, covered): pixels where one render shows cloth and the other the body,
        pixels where either shows cloth.
    """
    P = len(base_tri)
    count = 0
    hidden = 0
    covered = 0
    for p in range(P):
        g, t = base_tri[p], sub_tri[p]
        g_cloth = g >= 0 and g < num_faces
        t_cloth = t >= 0 and t < num_sub_faces
        if g_cloth or t_cloth:
            covered += 1
        if (g_cloth and t >= num_sub_faces) or (t_cloth and g >= num_faces):
            hidden += 1
        if g_cloth and t_cloth:
            count += 1
    pixels = np.empty(count, np.int64)
    e_b = np.empty(count)
    e_t = np.empty(count)
    uv_t = np.empty((count, 2))
    other = np.empty(count, np.bool_)
    points_g = np.zeros((count, 3))
    mat_b = np.zeros(count)
    has_rest = len(rest) > 0
    i = 0
    for p in range(P):
        g, t = base_tri[p], sub_tri[p]
        if not (g >= 0 and g < num_faces and t >= 0 and t < num_sub_faces):
            continue
        pixels[i] = p
        w0, w1, w2 = np.float64(base_bary[p, 0]), np.float64(base_bary[p, 1]), np.float64(base_bary[p, 2])
        a, b, c = faces[g, 0], faces[g, 1], faces[g, 2]
        # uv as a float32 image holds it, the difference in float64
        gu = np.float64(np.float32(w0 * uv[a, 0] + w1 * uv[b, 0] + w2 * uv[c, 0]))
        gv = np.float64(np.float32(w0 * uv[a, 1] + w1 * uv[b, 1] + w2 * uv[c, 1]))
        v0, v1, v2 = np.float64(sub_bary[p, 0]), np.float64(sub_bary[p, 1]), np.float64(sub_bary[p, 2])
        x, y, z = sub_faces[t, 0], sub_faces[t, 1], sub_faces[t, 2]
        bu = np.float64(np.float32(v0 * sub_uv[x, 0] + v1 * sub_uv[y, 0] + v2 * sub_uv[z, 0])) - gu
        bv = np.float64(np.float32(v0 * sub_uv[x, 1] + v1 * sub_uv[y, 1] + v2 * sub_uv[z, 1])) - gv
        tu = np.float64(np.float32(v0 * texcoords[x, 0] + v1 * texcoords[y, 0] + v2 * texcoords[z, 0]))
        tv = np.float64(np.float32(v0 * texcoords[x, 1] + v1 * texcoords[y, 1] + v2 * texcoords[z, 1]))
        e_b[i] = np.sqrt(bu * bu + bv * bv)
        e_t[i] = np.sqrt((tu - gu) * (tu - gu) + (tv - gv) * (tv - gv))
        uv_t[i, 0], uv_t[i, 1] = tu, tv
        other[i] = face_chart[g] != sub_face_chart[t]
        if has_rest:
            s = 0.0
            for k in range(3):
                pg = w0 * rest[a, k] + w1 * rest[b, k] + w2 * rest[c, k]
                points_g[i, k] = pg
                diff = v0 * sub_rest[x, k] + v1 * sub_rest[y, k] + v2 * sub_rest[z, k] - pg
                s += diff * diff
            mat_b[i] = np.sqrt(s)
        i += 1
    return pixels, e_b, e_t, uv_t, other, points_g, mat_b, hidden, covered


@_compiled
def _barycentric(px, py, uv, faces, f):
    """Barycentrics of uv point (px, py) in layout triangle f; -inf for a degenerate one."""
    ax, ay = uv[faces[f, 0], 0], uv[faces[f, 0], 1]
    v0x, v0y = uv[faces[f, 1], 0] - ax, uv[faces[f, 1], 1] - ay
    v1x, v1y = uv[faces[f, 2], 0] - ax, uv[faces[f, 2], 1] - ay
    v2x, v2y = px - ax, py - ay
    det = v0x * v1y - v0y * v1x
    w1 = (v2x * v1y - v2y * v1x) / det
    w2 = (v0x * v2y - v0y * v2x) / det
    w0 = 1.0 - w1 - w2
    if not (np.isfinite(w0) and np.isfinite(w1) and np.isfinite(w2)):
        return -np.inf, -np.inf, -np.inf
    return w0, w1, w2


@_compiled
def locate(points, ids, faces, uv, rest, ring_indptr, ring_indices):
    """The material point each uv point names (`MaterialMap`): the layout triangle it lies
    in, and the same barycentric combination of the rest positions.

    Args:
        points: (k,2) float64 uv. ids: (R,R) int32 the layout's UV raster (-1 empty).
        faces: (m,3) int64. uv: (n,2) float64. rest: (n,3) float64. ring_indptr,
        ring_indices: CSR rows of the triangles sharing a vertex with each triangle.

    Returns:
        material (k,3) float64 rest positions (0 where not inside), inside (k,) bool (the
        point lies in a triangle, to 1e-9; False: off the layout).
    """
    k = len(points)
    R = ids.shape[0]
    tri = np.full(k, -1, np.int64)
    bary = np.zeros((k, 3))
    inside = np.zeros(k, np.bool_)
    for i in range(k):
        px, py = points[i, 0], points[i, 1]
        col = min(max(np.int64(np.floor(px * R)), 0), R - 1)
        row = min(max(np.int64(np.floor(py * R)), 0), R - 1)
        # Most points lie in the triangle of their own texel.
        f = np.int64(ids[row, col])
        if f >= 0:
            w0, w1, w2 = _barycentric(px, py, uv, faces, f)
            tri[i], bary[i, 0], bary[i, 1], bary[i, 2] = f, w0, w1, w2
            if min(w0, min(w1, w2)) >= -1e-9:
                inside[i] = True
                continue
        # Near an edge of the layout's raster: the best of the 3x3 texels around.
        best, best_score = np.int64(-1), -np.inf
        b0 = b1 = b2 = 0.0
        for dr in range(-1, 2):
            r = min(max(row + dr, 0), R - 1)
            for dc in range(-1, 2):
                c = min(max(col + dc, 0), R - 1)
                f = np.int64(ids[r, c])
                if f < 0:
                    continue
                w0, w1, w2 = _barycentric(px, py, uv, faces, f)
                score = min(w0, min(w1, w2))
                if best < 0 or score > best_score:
                    best, best_score, b0, b1, b2 = f, score, w0, w1, w2
        if best < 0:
            tri[i] = -1
            continue
        tri[i], bary[i, 0], bary[i, 1], bary[i, 2] = best, b0, b1, b2
        if best_score >= -1e-9:
            inside[i] = True
            continue
        # Slivers thinner than a texel: the triangles sharing a vertex with the candidate.
        ring_best, ring_score = np.int64(-1), -np.inf
        r0 = r1 = r2 = 0.0
        for j in range(ring_indptr[best], ring_indptr[best + 1]):
            f = ring_indices[j]
            w0, w1, w2 = _barycentric(px, py, uv, faces, f)
            score = min(w0, min(w1, w2))
            if ring_best < 0 or score > ring_score:
                ring_best, ring_score, r0, r1, r2 = f, score, w0, w1, w2
        if ring_best >= 0 and (ring_score >= -1e-9 or ring_score > best_score):
            tri[i], bary[i, 0], bary[i, 1], bary[i, 2] = ring_best, r0, r1, r2
            inside[i] = ring_score >= -1e-9
    material = np.zeros((k, 3))
    for i in range(k):
        if inside[i]:
            a, b, c = faces[tri[i], 0], faces[tri[i], 1], faces[tri[i], 2]
            for j in range(3):
                material[i, j] = bary[i, 0] * rest[a, j] + bary[i, 1] * rest[b, j] + bary[i, 2] * rest[c, j]
    return material, inside
