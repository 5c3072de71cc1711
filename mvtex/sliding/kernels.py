"""Compiled kernels of the raster hit search (`mvtex.sliding.hits.find_hits_raster`).

The raster path tests each vertex ray against the triangles drawn in a small pixel window
around the vertex's projection (and their edge neighbours), exactly, in float64. Written
with NumPy array operations this builds a (rays, window) table, sorts it twice, expands it
four-fold and keeps every temporary; per ray in a compiled loop (numba) the same work is
a few dozen candidates in a small buffer, deduplicated with a per-face mark, each
intersected as it is found against the face's first corner and edges, computed once per
call. Nothing about the answer changes: the candidates, the
Möller–Trumbore arithmetic (operation for operation, no fast-math contraction) and the
tie-break keys are those of `sliding._window_pairs`, `sliding.intersect_pairs` and
`sliding.choose_hits`, which stay as the reference the tests compare with. The candidates
are not sorted: the nearest t does not depend on their order, and equal tie-break keys go
to the smaller face id, which is what the reference's ascending order gives.

Five kernels:

- `nearest_occluder`: the nearest hit t of each vertex's ray on the inferred base mesh,
  leaving out the base faces the vertex itself lies on (rule 2, the depth test).
- `first_hits`: the first gt hit of each ray with its tie-break (own chart, then facing
  the camera, then uv nearest the vertex's own T_G); the candidates also hold the faces
  the vertex lies on (gt and inferred share faces).
- `bin_faces` and `nearest_body_hit`: the body's faces binned to pixel tiles by their
  projection (`sliding.hits.bin_body`), and the first body hit of each ray among the faces
  of its tile: every face the ray can meet, so the body's answer is an exact ray cast's
  whatever the raster shows.
- `seen_from_inside`: `sliding.seen_from_inside` (area-weighted vertex normals, summed in
  the same order as `mesh.vertex_normals`, against the view direction) without its
  (m,3) and (n,3) temporaries.

numba is imported with this module; `mvtex.sliding.hits` imports it when it first runs a job.
The kernels are compiled on first use and cached by numba beside this module (as Python
caches bytecode in `__pycache__`): a few seconds once per installation, then a fraction of
a second per process.
"""

from __future__ import annotations

import numpy as np

from mvtex.util.compiled import compiled as _compiled

_BARY_EPS = 1e-9  # the same as sliding._BARY_EPS


@_compiled
def _window(tri_id, col, row, radius, neighbours, modulo, split, buf, mark, stamp):
    """Distinct ids >= 0 of the (2r+1)² window at (row, col) (clipped to the image) taken
    modulo `modulo` (> 0) and closed under `neighbours`, into buf[:count], in no particular
    order (every caller's answer is independent of it). Ids from `split` on (the body's)
    are left out. mark: (m,) int64 scratch, one entry per face id; an id is taken once per
    distinct `stamp` (a value mark never held for this ray: the ray's index + 1 for marks
    starting at 0)."""
    h, w = tri_id.shape
    count = 0
    for dr in range(-radius, radius + 1):
        r = min(max(row + dr, 0), h - 1)
        for dc in range(-radius, radius + 1):
            c = min(max(col + dc, 0), w - 1)
            f = tri_id[r, c]
            if f < 0 or f >= split:
                continue
            if modulo > 0:
                f = f % modulo
            if mark[f] != stamp:
                mark[f] = stamp
                buf[count] = f
                count += 1
    drawn = count
    for i in range(drawn):
        for k in range(3):
            f = neighbours[buf[i], k]
            if f >= 0 and mark[f] != stamp:
                mark[f] = stamp
                buf[count] = f
                count += 1
    return count


@_compiled
def _corner_edges(positions, faces):
    """(m,9) float64 per face: its first corner p0 and edges e1 = p1 - p0, e2 = p2 - p0 (the
    subtractions `_intersect` would repeat for every ray that tests the face)."""
    m = len(faces)
    out = np.empty((m, 9))
    for f in range(m):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        for k in range(3):
            out[f, k] = positions[a, k]
            out[f, 3 + k] = positions[b, k] - positions[a, k]
            out[f, 6 + k] = positions[c, k] - positions[a, k]
    return out


@_compiled
def _intersect(ox, oy, oz, dx, dy, dz, corner_edges, f):
    """`sliding.intersect_pairs` for one (ray, triangle): (t or inf, b1, b2, facing);
    corner_edges from `_corner_edges`."""
    p0x, p0y, p0z = corner_edges[f, 0], corner_edges[f, 1], corner_edges[f, 2]
    e1x, e1y, e1z = corner_edges[f, 3], corner_edges[f, 4], corner_edges[f, 5]
    e2x, e2y, e2z = corner_edges[f, 6], corner_edges[f, 7], corner_edges[f, 8]
    px = dy * e2z - dz * e2y
    py = dz * e2x - dx * e2z
    pz = dx * e2y - dy * e2x
    det = e1x * px + e1y * py + e1z * pz
    sx, sy, sz = ox - p0x, oy - p0y, oz - p0z
    qx = sy * e1z - sz * e1y
    qy = sz * e1x - sx * e1z
    qz = sx * e1y - sy * e1x
    inv = 1.0 / det
    b1 = (sx * px + sy * py + sz * pz) * inv
    b2 = (dx * qx + dy * qy + dz * qz) * inv
    t = (e2x * qx + e2y * qy + e2z * qz) * inv
    hit = det != 0 and b1 >= -_BARY_EPS and b2 >= -_BARY_EPS and b1 + b2 <= 1 + _BARY_EPS and t > 0
    return (t if hit else np.inf), b1, b2, -det


@_compiled
def nearest_occluder(origin, dirs, pixels, tri_id, radius, neighbours, modulo, split, host_keys, vertices,
                     positions, faces):
    """Per ray k: the smallest t > 0 at which dirs[k] (from `origin`) hits a base face of
    the window around pixels[k] in `tri_id` (subdivided ids, taken modulo `modulo`), other
    than the faces hosting vertices[k] (key vertex * modulo + face in sorted `host_keys`).

    Args:
        origin: (3,) float64. dirs: (k,3) float64, t = 1 at the vertex. pixels: (k,2) float64.
        tri_id: (H,W) int ids (-1 background). radius: window half-size. neighbours: (m,3)
        int64 base face neighbours (-1 none). modulo: m, the number of base faces.
        split: the raster id of the body's first face (ids from it on are left out: the
        body is searched by `nearest_body_hit`); larger than every id without a body.
        host_keys: sorted int64. vertices: (k,) int64. positions: (n,3) float64 base
        inferred positions. faces: (m,3) int64 base faces.

    Returns:
        (k,) float64 t (inf where nothing is hit).
    """
    k = len(dirs)
    out = np.full(k, np.inf)
    buf = np.empty(4 * (2 * radius + 1) ** 2, np.int64)
    mark = np.zeros(len(neighbours), np.int64)
    hosted = np.zeros(len(neighbours), np.int64)
    corner_edges = _corner_edges(positions, faces)
    ox, oy, oz = origin[0], origin[1], origin[2]
    for i in range(k):
        count = _window(tri_id, np.int64(np.rint(pixels[i, 0])), np.int64(np.rint(pixels[i, 1])), radius,
                        neighbours, modulo, split, buf, mark, i + 1)
        # The vertex's host keys are one sorted run of host_keys: mark its host faces.
        lo = np.searchsorted(host_keys, vertices[i] * modulo)
        hi = np.searchsorted(host_keys, (vertices[i] + 1) * modulo)
        for h in range(lo, hi):
            hosted[host_keys[h] - vertices[i] * modulo] = i + 1
        best = np.inf
        for j in range(count):
            f = buf[j]
            if hosted[f] == i + 1:
                continue
            t = _intersect(ox, oy, oz, dirs[i, 0], dirs[i, 1], dirs[i, 2], corner_edges, f)[0]
            if t < best:
                best = t
        out[i] = best
    return out


@_compiled
def first_hits(origin, dirs, pixels, tri_id, radius, neighbours, positions, faces, num_cloth, t_body,
               vert_chart, face_chart, vert_uv, face_uv, host_keys, vertices):
    """Per ray k: the nearest hit of dirs[k] on the faces of the window around pixels[k]
    in `tri_id` and on the faces hosting vertices[k] (gt and inferred share the faces:
    where they are close these hold the hit, even as slivers no pixel centre samples),
    ties broken as `sliding.choose_hits` does with uv given.

    Args:
        origin, dirs, pixels, tri_id, radius, neighbours: as `nearest_occluder` (ids are
        base face ids, no modulo). host_keys, vertices: as `nearest_occluder` (keys
        v * num_cloth + f). positions: (n,3) float64 gt positions. faces: (m,3) int64.
        num_cloth: m (raster ids from it on are the body's, left out). t_body: (k,)
        float64 each ray's first body hit (`nearest_body_hit`; inf without a body): a ray
        whose first cloth hit lies past it has none (exact ties, within the relative 1e-9
        of the cloth's own ties, go to the cloth).
        vert_chart: (k,) int64 chart of each ray's vertex. face_chart: (m,) int64.
        vert_uv: (k,2) float64 the vertex's T_G. face_uv: (n,2) float64 gt uv.

    Returns:
        tri (k,) int64 (-1 = no hit), bary (k,3) float64, back (k,) bool.
    """
    k = len(dirs)
    tri = np.full(k, -1, np.int64)
    bary = np.zeros((k, 3))
    back = np.zeros(k, np.bool_)
    # The window closed under neighbours, and the most faces any vertex lies on.
    most, run = 0, 0
    for h in range(len(host_keys)):
        run = run + 1 if h > 0 and host_keys[h] // num_cloth == host_keys[h - 1] // num_cloth else 1
        most = max(most, run)
    size = 4 * (2 * radius + 1) ** 2 + most
    buf = np.empty(size, np.int64)
    ts = np.empty(size)
    b1s = np.empty(size)
    b2s = np.empty(size)
    facing = np.empty(size)
    mark = np.zeros(len(neighbours), np.int64)
    corner_edges = _corner_edges(positions, faces)
    ox, oy, oz = origin[0], origin[1], origin[2]
    for i in range(k):
        count = _window(tri_id, np.int64(np.rint(pixels[i, 0])), np.int64(np.rint(pixels[i, 1])), radius,
                        neighbours, 0, num_cloth, buf, mark, i + 1)
        lo = np.searchsorted(host_keys, vertices[i] * num_cloth)
        hi = np.searchsorted(host_keys, (vertices[i] + 1) * num_cloth)
        for h in range(lo, hi):
            f = host_keys[h] - vertices[i] * num_cloth
            if mark[f] != i + 1:
                mark[f] = i + 1
                buf[count] = f
                count += 1
        t_min = np.inf
        for j in range(count):
            ts[j], b1s[j], b2s[j], facing[j] = _intersect(ox, oy, oz, dirs[i, 0], dirs[i, 1], dirs[i, 2],
                                                          corner_edges, buf[j])
            if ts[j] < t_min:
                t_min = ts[j]
        if t_min == np.inf or t_min > t_body[i] * (1 + 1e-9):
            continue
        limit = t_min * (1 + 1e-9)
        best_key = np.inf
        best = -1
        for j in range(count):
            t = ts[j]
            if not (t < np.inf and t <= limit):
                continue
            f = buf[j]
            b1, b2 = b1s[j], b2s[j]
            key = 4.0 * (face_chart[f] != vert_chart[i]) + 2.0 * (facing[j] > 0)
            w0 = 1 - b1 - b2
            a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
            u = w0 * face_uv[a, 0] + b1 * face_uv[b, 0] + b2 * face_uv[c, 0] - vert_uv[i, 0]
            v = w0 * face_uv[a, 1] + b1 * face_uv[b, 1] + b2 * face_uv[c, 1] - vert_uv[i, 1]
            key = key + min(np.sqrt(u * u + v * v), 1.0)
            # Equal keys go to the smaller face id, as in `choose_hits`' ascending order.
            if key < best_key or (key == best_key and f < buf[best]):
                best_key = key
                best = j
        if best < 0:
            continue
        tri[i] = buf[best]
        b1, b2 = b1s[best], b2s[best]
        bary[i, 0] = 1 - b1 - b2
        bary[i, 1] = b1
        bary[i, 2] = b2
        back[i] = facing[best] > 0
    return tri, bary, back


@_compiled
def seen_from_inside(positions, faces, origin):
    """(n,) bool: the area-weighted vertex normal of `positions` ((n,3) float64; `faces`
    (m,3) int64, CCW from outside) points away from `origin` ((3,) float64)."""
    n = len(positions)
    acc = np.zeros((n, 3))
    for f in range(len(faces)):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        ux, uy, uz = positions[b, 0] - positions[a, 0], positions[b, 1] - positions[a, 1], positions[b, 2] - positions[a, 2]
        vx, vy, vz = positions[c, 0] - positions[a, 0], positions[c, 1] - positions[a, 1], positions[c, 2] - positions[a, 2]
        nx = uy * vz - uz * vy
        ny = uz * vx - ux * vz
        nz = ux * vy - uy * vx
        for k in range(3):
            v = faces[f, k]
            acc[v, 0] += nx
            acc[v, 1] += ny
            acc[v, 2] += nz
    out = np.zeros(n, np.bool_)
    for i in range(n):
        x, y, z = acc[i, 0], acc[i, 1], acc[i, 2]
        norm = max(np.sqrt(x * x + y * y + z * z), 1e-300)
        out[i] = ((x / norm) * (positions[i, 0] - origin[0]) + (y / norm) * (positions[i, 1] - origin[1])
                  + (z / norm) * (positions[i, 2] - origin[2])) > 0
    return out


@_compiled
def nearest_body_hit(origin, dirs, pixels, ahead, c0, r0, tile, columns, rows, start, cell_faces, everywhere,
                     positions, faces):
    """Per ray k: the smallest t > 0 at which dirs[k] (from `origin`) hits a face of the
    body, testing the faces binned to the tile of pixels[k] and those in `everywhere`
    (`sliding.hits.BodyBins`); a ray not `ahead` (its point not binned: behind the
    camera or far outside the image) is tested against every face.

    Args:
        origin: (3,) float64. dirs: (k,3) float64. pixels: (k,2) float64. ahead: (k,) bool.
        c0, r0, tile, columns, rows: the tile grid (`BodyBins`). start: (cells + 1,) int64
        CSR offsets into cell_faces (int64). everywhere: (e,) int64 faces of every tile.
        positions: (nb,3) float64. faces: (mb,3) int64.

    Returns:
        (k,) float64 t (inf where the body is not hit).
    """
    k = len(dirs)
    out = np.full(k, np.inf)
    corner_edges = _corner_edges(positions, faces)
    ox, oy, oz = origin[0], origin[1], origin[2]
    for i in range(k):
        dx, dy, dz = dirs[i, 0], dirs[i, 1], dirs[i, 2]
        best = np.inf
        if not ahead[i]:
            for f in range(len(faces)):
                t = _intersect(ox, oy, oz, dx, dy, dz, corner_edges, f)[0]
                if t < best:
                    best = t
            out[i] = best
            continue
        col = min(max(np.int64(np.floor((pixels[i, 0] - c0) / tile)), 0), columns - 1)
        row = min(max(np.int64(np.floor((pixels[i, 1] - r0) / tile)), 0), rows - 1)
        cell = row * columns + col
        for j in range(start[cell], start[cell + 1]):
            t = _intersect(ox, oy, oz, dx, dy, dz, corner_edges, cell_faces[j])[0]
            if t < best:
                best = t
        for j in range(len(everywhere)):
            t = _intersect(ox, oy, oz, dx, dy, dz, corner_edges, everywhere[j])[0]
            if t < best:
                best = t
        out[i] = best
    return out


@_compiled
def bin_faces(proj, z, faces, lo0, lo1, tile, columns, rows, margin):
    """`sliding.hits.bin_body` after the projection: proj (nb,2) float64 and z (nb,)
    float64 the body's projected corners and depths, faces (mb,3) int64, the grid's first
    corner (lo0, lo1), tile size, size in tiles, margin in pixels. Returns start
    (columns * rows + 1,) int64, the faces tile by tile (each tile's in increasing order,
    as the NumPy formulation's stable sort leaves them) and the faces reaching behind the
    camera's plane, the same arrays as the NumPy formulation."""
    m = len(faces)
    cells = columns * rows
    box = np.empty((m, 4), np.int64)
    keep = np.zeros(m, np.bool_)
    behind = np.zeros(m, np.bool_)
    start = np.zeros(cells + 1, np.int64)
    for f in range(m):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        if not (z[a] > 0 and z[b] > 0 and z[c] > 0):
            behind[f] = z[a] > 0 or z[b] > 0 or z[c] > 0
            continue
        c_lo = np.floor((min(proj[a, 0], proj[b, 0], proj[c, 0]) - margin - lo0) / tile)
        c_hi = np.floor((max(proj[a, 0], proj[b, 0], proj[c, 0]) + margin - lo0) / tile)
        r_lo = np.floor((min(proj[a, 1], proj[b, 1], proj[c, 1]) - margin - lo1) / tile)
        r_hi = np.floor((max(proj[a, 1], proj[b, 1], proj[c, 1]) + margin - lo1) / tile)
        if not (c_hi >= 0 and c_lo <= columns - 1 and r_hi >= 0 and r_lo <= rows - 1):
            continue
        keep[f] = True
        box[f, 0] = np.int64(min(max(c_lo, 0), columns - 1))
        box[f, 1] = np.int64(min(max(c_hi, 0), columns - 1))
        box[f, 2] = np.int64(min(max(r_lo, 0), rows - 1))
        box[f, 3] = np.int64(min(max(r_hi, 0), rows - 1))
        for r in range(box[f, 2], box[f, 3] + 1):
            for col in range(box[f, 0], box[f, 1] + 1):
                start[r * columns + col + 1] += 1
    for j in range(cells):
        start[j + 1] += start[j]
    pos = start[:-1].copy()
    out = np.empty(start[cells], np.int64)
    for f in range(m):
        if not keep[f]:
            continue
        for r in range(box[f, 2], box[f, 3] + 1):
            for col in range(box[f, 0], box[f, 1] + 1):
                cell = r * columns + col
                out[pos[cell]] = f
                pos[cell] += 1
    return start, out, np.flatnonzero(behind).astype(np.int64)
