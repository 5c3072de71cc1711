"""Texture sliding (DESIGN §5 steps 1-7): per (pose, camera), new texture coordinates T_N
for the smooth inferred mesh so that, seen from the camera, it shows the ground-truth
cloth's material at the right pixels.

For each vertex of the (subdivided) inferred mesh the ray from the camera centre through
it is intersected with the ground-truth mesh; T_N is the gt uv at the first hit and the
stored displacement is d = T_N - T_G. The search for the hit triangle uses rasterization
instead of a BVH: the gt triangle ids rendered around the vertex's projection are the
candidates, and the exact float64 ray is intersected with each (Möller–Trumbore), so the
answer is that of an exact ray cast. The same candidate trick gives the depth test that
decides whether the vertex itself is visible.

`slide_pose` does one (pose, camera); `mvtex.sliding.dataset.slide_dataset` streams a whole
dataset into a texcoord set (DESIGN §4). Rasterization goes through `mvtex.render.raster` with a
`GLContext` the caller passes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from mvtex.data.camera import Camera
from mvtex.data.mesh import vertex_normals
from mvtex.render.raster import body_offsets, rasterize_pair
from mvtex.sliding.kernels import bin_faces, first_hits, nearest_occluder
from mvtex.sliding.kernels import nearest_body_hit as kernel
from mvtex.sliding.kernels import seen_from_inside as compiled_seen_from_inside
from mvtex.sliding.options import SlideOptions
from mvtex.sliding.topology import BodyTopology, SlideTopology

if TYPE_CHECKING:
    from mvtex.render.context import GLContext

_BARY_EPS = 1e-9


def intersect_pairs(origin: np.ndarray, dirs: np.ndarray, positions: np.ndarray, faces: np.ndarray,
                    tri: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Möller–Trumbore in float64, ray k against triangle tri[k], for k in range(p).

    Args:
        origin: (3,) common ray origin (the camera centre).
        dirs: (p,3) ray directions; t is measured in units of each direction's length.
        positions: (n,3) mesh positions. faces: (m,3) triangles. tri: (p,) triangle ids (>= 0).

    Returns:
        t (p,) (inf where the ray misses the triangle or hits it at t <= 0),
        b1, b2 (p,) barycentric weights of corners 1 and 2 at the hit,
        facing (p,) float: (face normal) · dir, > 0 for a triangle facing away from the ray.
    """
    f = faces[tri]
    p0 = positions[f[:, 0]]
    e1 = positions[f[:, 1]] - p0
    e2 = positions[f[:, 2]] - p0
    dx, dy, dz = dirs[:, 0], dirs[:, 1], dirs[:, 2]
    px = dy * e2[:, 2] - dz * e2[:, 1]
    py = dz * e2[:, 0] - dx * e2[:, 2]
    pz = dx * e2[:, 1] - dy * e2[:, 0]
    det = e1[:, 0] * px + e1[:, 1] * py + e1[:, 2] * pz
    s = origin - p0
    qx = s[:, 1] * e1[:, 2] - s[:, 2] * e1[:, 1]
    qy = s[:, 2] * e1[:, 0] - s[:, 0] * e1[:, 2]
    qz = s[:, 0] * e1[:, 1] - s[:, 1] * e1[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        b1 = (s[:, 0] * px + s[:, 1] * py + s[:, 2] * pz) * inv
        b2 = (dx * qx + dy * qy + dz * qz) * inv
        t = (e2[:, 0] * qx + e2[:, 1] * qy + e2[:, 2] * qz) * inv
    hit = (det != 0) & (b1 >= -_BARY_EPS) & (b2 >= -_BARY_EPS) & (b1 + b2 <= 1 + _BARY_EPS) & (t > 0)
    # (e1 x e2) · d = -det (scalar triple product): the sign tells the facing for free.
    return np.where(hit, t, np.inf), b1, b2, -det


def _window_pairs(tri_id: np.ndarray, pixels: np.ndarray, radius: int,
                  neighbours: np.ndarray | None = None, modulo: int | None = None,
                  split: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Distinct triangle ids in the (2r+1)² window around each pixel (and their edge
    neighbours if given), as (ray, tri) pairs sorted by ray. With `modulo`, the raster's
    ids (>= 0) are taken modulo it first (subdivided face ids -> base face ids). Ids from
    `split` on (the body's) are left out."""
    H, W = tri_id.shape
    col = np.rint(pixels[:, 0]).astype(np.int64)
    row = np.rint(pixels[:, 1]).astype(np.int64)
    off = np.arange(-radius, radius + 1)
    rr = np.clip(row[:, None, None] + off[None, :, None], 0, H - 1)
    cc = np.clip(col[:, None, None] + off[None, None, :], 0, W - 1)
    ids = tri_id[rr, cc].reshape(len(pixels), -1)
    if split is not None:
        ids = np.where(ids >= split, -1, ids)
    if modulo is not None:
        ids = np.where(ids >= 0, ids % modulo, -1)
    if neighbours is not None:
        ids = np.sort(ids, axis=1)
        ids[:, 1:][ids[:, 1:] == ids[:, :-1]] = -1
        # Each distinct id with its edge neighbours, looked up in one table whose last row
        # (index -1) is all -1: background and repeated ids add nothing.
        closed = np.full((len(neighbours) + 1, 4), -1, np.int64)
        closed[:-1, 0] = np.arange(len(neighbours))
        closed[:-1, 1:] = neighbours
        ids = closed[ids].reshape(len(pixels), -1)
    ids = np.sort(ids, axis=1)
    keep = ids >= 0
    keep[:, 1:] &= ids[:, 1:] != ids[:, :-1]
    ray = np.broadcast_to(np.arange(len(pixels))[:, None], ids.shape)[keep]
    return ray, ids[keep]


def _with_hosts(ray: np.ndarray, tri: np.ndarray, vertices: np.ndarray, host_keys: np.ndarray,
                m: int) -> tuple[np.ndarray, np.ndarray]:
    """(ray, tri) pairs with each ray's host faces added (the base faces vertices[ray] lies
    on, from the sorted keys v * m + f), distinct and sorted by ray then face."""
    lo = np.searchsorted(host_keys, vertices * m)
    hi = np.searchsorted(host_keys, (vertices + 1) * m)
    count = hi - lo
    host_ray = np.repeat(np.arange(len(vertices)), count)
    host = host_keys[np.repeat(lo, count) + np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)]
    keys = np.unique(np.r_[ray * m + tri, host_ray * m + (host - vertices[host_ray] * m)])
    return keys // m, keys % m


def _first_per_ray(ray: np.ndarray, key: np.ndarray, num_rays: int) -> tuple[np.ndarray, np.ndarray]:
    """For pairs sorted by ray: per ray, the index of the first pair with the smallest key.

    Returns (best (num_rays,) pair index or -1, best_key (num_rays,) inf where none)."""
    best_key = np.full(num_rays, np.inf)
    best = np.full(num_rays, -1)
    if len(ray) == 0:
        return best, best_key
    starts = np.flatnonzero(np.r_[True, ray[1:] != ray[:-1]])
    best_key[ray[starts]] = np.minimum.reduceat(key, starts)
    idx = np.flatnonzero((key == best_key[ray]) & np.isfinite(key))
    r = ray[idx]
    first = idx[np.r_[True, r[1:] != r[:-1]]] if len(idx) else idx
    best[ray[first]] = first
    return best, best_key


_TILE = 8  # pixels per side of a body bin
_BIN_MARGIN = 1.0  # pixels added around a face's projected box (far above rounding)


@dataclass(frozen=True)
class BodyBins:
    """The body's faces binned by where they project, for the rays through a set of pixels.

    A ray from the camera centre towards a point in front of the camera meets, at t > 0,
    only points that project to that point's pixel; a face with all corners in front of
    the camera can be hit only where its projected corners' box (grown by a margin) holds
    the pixel. So the faces binned to a pixel's tile are every face its ray can hit, except
    faces reaching behind the camera's plane, which are in `everywhere`; faces wholly
    behind it are never hit (nor kept).

    Attributes:
        c0, r0: pixel of the grid's first tile corner. tile: tile size in pixels.
        columns, rows: the grid's size in tiles (it covers the pixels it was made for).
        start: (columns * rows + 1,) int64 offsets of each tile's faces in `faces`.
        faces: int64 face ids, tile by tile. everywhere: int64 faces of every tile.
    """

    c0: float
    r0: float
    tile: int
    columns: int
    rows: int
    start: np.ndarray
    faces: np.ndarray
    everywhere: np.ndarray

    def cells(self, pixels: np.ndarray) -> np.ndarray:
        """(k,) int64 tile index of each pixel (clipped to the grid)."""
        col = np.clip(np.floor((pixels[:, 0] - self.c0) / self.tile), 0, self.columns - 1).astype(np.int64)
        row = np.clip(np.floor((pixels[:, 1] - self.r0) / self.tile), 0, self.rows - 1).astype(np.int64)
        return row * self.columns + col


def bin_body(camera: Camera, positions: np.ndarray, faces: np.ndarray, pixels: np.ndarray,
             tile: int = _TILE, *, compiled: bool = True) -> BodyBins:
    """`BodyBins` of the body (positions (nb,3), faces (mb,3)) for rays through `pixels`
    ((k,2) finite projections of points in front of `camera`). `compiled`: bin with
    `mvtex.sliding.kernels.bin_faces` (False: NumPy; the same bins)."""
    faces = np.asarray(faces, np.int64)
    if len(pixels):
        lo, hi = np.floor(pixels.min(axis=0)), np.floor(pixels.max(axis=0))
    else:
        lo = hi = np.zeros(2)
    columns = int((hi[0] - lo[0]) // tile) + 1
    rows = int((hi[1] - lo[1]) // tile) + 1
    proj, z = camera.project(positions)
    if compiled:

        start, binned, everywhere = bin_faces(np.ascontiguousarray(proj), np.ascontiguousarray(z), faces,
                                              float(lo[0]), float(lo[1]), float(tile), columns, rows, _BIN_MARGIN)
        return BodyBins(c0=float(lo[0]), r0=float(lo[1]), tile=int(tile), columns=columns, rows=rows, start=start,
                        faces=binned, everywhere=everywhere)
    zf = z[faces]
    ahead = np.all(zf > 0, axis=1)
    everywhere = np.flatnonzero(~ahead & np.any(zf > 0, axis=1))
    f = np.flatnonzero(ahead)
    corners = proj[faces[f]]
    # Tile range of each face's box, clipped to the grid; faces off the grid are dropped.
    c_lo = np.floor((corners[:, :, 0].min(axis=1) - _BIN_MARGIN - lo[0]) / tile)
    c_hi = np.floor((corners[:, :, 0].max(axis=1) + _BIN_MARGIN - lo[0]) / tile)
    r_lo = np.floor((corners[:, :, 1].min(axis=1) - _BIN_MARGIN - lo[1]) / tile)
    r_hi = np.floor((corners[:, :, 1].max(axis=1) + _BIN_MARGIN - lo[1]) / tile)
    on = (c_hi >= 0) & (c_lo <= columns - 1) & (r_hi >= 0) & (r_lo <= rows - 1)
    f = f[on]
    c_lo = np.clip(c_lo[on], 0, columns - 1).astype(np.int64)
    c_hi = np.clip(c_hi[on], 0, columns - 1).astype(np.int64)
    r_lo = np.clip(r_lo[on], 0, rows - 1).astype(np.int64)
    r_hi = np.clip(r_hi[on], 0, rows - 1).astype(np.int64)
    width = c_hi - c_lo + 1
    count = width * (r_hi - r_lo + 1)
    owner = np.repeat(np.arange(len(f)), count)
    local = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)
    cell = (r_lo[owner] + local // width[owner]) * columns + c_lo[owner] + local % width[owner]
    order = np.argsort(cell, kind="stable")
    start = np.zeros(columns * rows + 1, np.int64)
    np.cumsum(np.bincount(cell, minlength=columns * rows), out=start[1:])
    return BodyBins(c0=float(lo[0]), r0=float(lo[1]), tile=int(tile), columns=columns, rows=rows, start=start,
                    faces=f[owner[order]].astype(np.int64), everywhere=everywhere.astype(np.int64))


def nearest_body_hit(camera: Camera, positions: np.ndarray, faces: np.ndarray, points: np.ndarray, *,
                     compiled: bool = True) -> np.ndarray:
    """(k,) float64 t of the first point where the ray from the camera centre towards each
    of `points` (k,3) meets the body (positions (nb,3), faces (mb,3)), with t = 1 at the
    point (inf: never). Exact: every face the ray can meet is tested in float64
    (Möller–Trumbore, as the cloth hits): the faces binned to its pixel (`bin_body`);
    a point behind the camera or far outside its image is tested against every face.
    The body hides the point when t < 1 (DESIGN §5 "The body")."""
    positions = np.ascontiguousarray(positions, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    origin = np.ascontiguousarray(camera.center, dtype=np.float64)
    points = np.asarray(points, np.float64)
    dirs = np.ascontiguousarray(points - origin)
    pixels, z = camera.project(points)
    # Rays through the image or near it are binned (the grid's size stays bounded by the
    # image's); any other is tested against every face.
    W, H = camera.width, camera.height
    with np.errstate(invalid="ignore"):
        ahead = (z > 0) & (pixels[:, 0] > -W) & (pixels[:, 0] < 2 * W) & (pixels[:, 1] > -H) & (pixels[:, 1] < 2 * H)
    pixels = np.ascontiguousarray(np.where(ahead[:, None], pixels, 0.0))
    bins = bin_body(camera, positions, faces, pixels[ahead], compiled=compiled)
    if compiled:

        return kernel(origin, dirs, pixels, ahead, bins.c0, bins.r0, bins.tile, bins.columns, bins.rows, bins.start,
                      bins.faces, bins.everywhere, positions, faces)
    cell = bins.cells(pixels)
    lo, hi = bins.start[cell], bins.start[cell + 1]
    count = np.where(ahead, hi - lo, 0)
    ray = np.repeat(np.arange(len(points)), count)
    tri = bins.faces[np.repeat(lo, count) + np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)]
    behind = np.flatnonzero(~ahead)
    ray = np.concatenate([ray, np.repeat(np.flatnonzero(ahead), len(bins.everywhere)),
                          np.repeat(behind, len(faces))])
    tri = np.concatenate([tri, np.tile(bins.everywhere, int(ahead.sum())), np.tile(np.arange(len(faces)), len(behind))])
    t = intersect_pairs(origin, dirs[ray], positions, faces, tri)[0]
    out = np.full(len(points), np.inf)
    np.minimum.at(out, ray, t)
    return out


@dataclass
class Hits:
    """Result of the hit search for the subdivided inferred vertices (n').

    Attributes:
        visible: (n',) bool, the vertex passed both visibility rules.
        tri: (n',) int64 gt triangle of the first hit (-1 if none).
        bary: (n',3) float64 barycentrics of the hit in `tri`.
        back: (n',) bool, the hit triangle faces away from the camera.
        from_inside: (n',) bool, the inferred vertex itself is seen from the garment's
            inside (its normal faces away from the camera, e.g. looking into a collar).
    """

    visible: np.ndarray
    tri: np.ndarray
    bary: np.ndarray
    back: np.ndarray
    from_inside: np.ndarray


def seen_from_inside(X: np.ndarray, faces: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """(n,) bool: the area-weighted vertex normal of X (faces CCW from outside) points away
    from the camera at `origin`."""

    return np.einsum("ij,ij->i", vertex_normals(X, faces), X - origin) > 0


def choose_hits(origin: np.ndarray, dirs: np.ndarray, gt: np.ndarray, gt_faces: np.ndarray, ray: np.ndarray,
                tri: np.ndarray, vert_chart: np.ndarray, gt_chart: np.ndarray, vert_uv: np.ndarray | None = None,
                gt_uv: np.ndarray | None = None, t_body: np.ndarray | None = None):
    """Nearest hit per ray among its candidate (ray, tri) pairs. Exact ties (a ray through
    a gt vertex or edge) prefer a triangle of the vertex's own chart, then one facing the
    camera, then (given `vert_uv` (k,2) and `gt_uv` (n,2)) the one whose uv at the hit is
    nearest the vertex's own T_G: where a chart meets itself along a seam, both sides name
    the same material and the vertex keeps its own side's coordinates.
    With `t_body` (k,) (each ray's first body hit, `nearest_body_hit`), a ray whose
    nearest cloth hit lies past it has none (exact ties, within the relative 1e-9 of the
    cloth's own ties, go to the cloth).
    Returns tri (k,) (-1 = no hit), bary (k,3), back (k,) bool."""
    k = len(dirs)
    t, b1, b2, facing = intersect_pairs(origin, dirs[ray], gt, gt_faces, tri)
    _, t_min = _first_per_ray(ray, t, k)
    if t_body is not None:
        t_min = np.where(t_min > t_body * (1 + 1e-9), -np.inf, t_min)  # the body first: no pair is near
    # Only the pairs tied for the nearest hit compete on the tie-break key; they keep their
    # order, so the first best pair is the same as over all pairs.
    near = np.flatnonzero(np.isfinite(t) & (t <= t_min[ray] * (1 + 1e-9)))
    ray, tri, b1, b2 = ray[near], tri[near], b1[near], b2[near]
    back = facing[near] > 0
    other = gt_chart[tri] != vert_chart[ray]
    key = 4.0 * other + 2.0 * back
    if vert_uv is not None and gt_uv is not None:
        corners = gt_uv[gt_faces[tri]]
        w = np.stack([1 - b1 - b2, b1, b2], axis=1)
        hit_uv = np.einsum("kj,kjc->kc", w, corners)
        key = key + np.minimum(np.linalg.norm(hit_uv - vert_uv[ray], axis=1), 1.0)
    best, _ = _first_per_ray(ray, key, k)
    found = best >= 0
    sel = best[found]
    out_tri = np.full(k, -1, np.int64)
    out_tri[found] = tri[sel]
    bary = np.zeros((k, 3))
    bary[found] = np.stack([1 - b1[sel] - b2[sel], b1[sel], b2[sel]], axis=1)
    out_back = np.zeros(k, bool)
    out_back[found] = back[sel]
    return out_tri, bary, out_back


def owning_vertices(owned: np.ndarray, topo: SlideTopology, camera: Camera, pixels: np.ndarray,
                    depth: np.ndarray) -> np.ndarray:
    """Rule 1 of visibility (the paper's): the vertices of an (subdivided) inferred triangle
    that owns at least one pixel, and whose projection lies in the image.

    Args:
        owned: (m',) bool, which subdivided faces own a pixel.
        pixels, depth: (n',2) and (n',) the vertices' projections (`Camera.project`).

    Returns:
        (k,) int64 vertex indices, increasing.
    """
    touched = np.zeros(len(topo.uv), bool)
    touched[topo.faces[owned].ravel()] = True
    return np.flatnonzero(touched & camera.in_image(pixels, depth))


def in_front(t_first: np.ndarray, options: SlideOptions) -> np.ndarray:
    """Rule 2 of visibility: nothing of the inferred mesh lies before the vertex on its ray,
    given the nearest occluder's t (t = 1 at the vertex, inf for none), with the relative
    tolerance `options.depth_tolerance`. (k,) bool."""
    return t_first >= 1 - options.depth_tolerance


def find_hits_raster(ctx: GLContext, gt: np.ndarray, inferred: np.ndarray, faces: np.ndarray, X: np.ndarray,
                     topo: SlideTopology, camera: Camera, options: SlideOptions, *, compiled: bool = True,
                     body: tuple[np.ndarray, BodyTopology] | None = None) -> Hits:
    """Visibility and first gt hits by rasterization + exact candidate intersection.

    Args:
        ctx: the GL context.
        gt, inferred: (n,3) float64 base positions. faces: (m,3) base faces.
        X: (n',3) float64 subdivided inferred positions.
        compiled: search the candidates with the compiled kernels of `mvtex.sliding.kernels`
            (the default); False runs the NumPy formulation (`_window_pairs`,
            `intersect_pairs`, `choose_hits`), which gives the same answer, slower.
        body: (positions (nb,3), `body_topology(...)`) of the wearer's body in this pose:
            drawn into both rasters (a pixel where it is nearest shows no cloth); a vertex
            whose ray meets it before the vertex (t < 1) is not visible (rule 2), a ray
            that meets it before the gt cloth has no hit (rule 3). The body's first hit on
            each ray comes from an exact ray cast (`nearest_body_hit`: every body face
            the ray can meet, in float64), not from the raster windows, which miss faces
            seen edge-on at the body's silhouette.
    """

    n = len(X)
    m = len(faces)
    origin = camera.center
    pixels, z = camera.project(X)
    gt_pixels = camera.project(gt)[0]
    bounds = np.concatenate([gt_pixels, pixels])
    occluder = None
    split_base = split_sub = np.iinfo(np.int64).max
    if body is not None:
        body_positions = np.asarray(body[0], np.float64)
        occluder = (body_positions, body[1].faces)
        split_base, split_sub = body_offsets(m, len(topo.levels) - 1)
    # Ids of the subdivided inferred faces (they give rule 1 directly); the base face of
    # subdivided face k is k % m (children keep their parent modulo m). Both corners sets
    # bound the read-back region (the inferred base vertices are among X's first n).
    gt_ids, sub_ids = rasterize_pair(ctx, gt, inferred, faces, camera, levels=len(topo.levels) - 1,
                                     pixels=bounds, occluder=occluder)
    owned = np.zeros(len(topo.faces), bool)
    owned[sub_ids[(sub_ids >= 0) & (sub_ids < split_sub)]] = True
    cand = owning_vertices(owned, topo, camera, pixels, z)
    neighbours = topo.face_neighbours
    faces = np.asarray(faces, np.int64)
    # Rule 2: nothing of the inferred mesh in front of the vertex along its ray (t = 1 at
    # the vertex), up to the depth tolerance, and nothing of the body before it at all.
    # Candidate occluders: the base inferred triangles drawn around its projection (the
    # same surface as their subdivided children).
    dirs = X[cand] - origin
    if compiled:

        faces64 = np.ascontiguousarray(faces, dtype=np.int64)
        origin64 = np.ascontiguousarray(origin, dtype=np.float64)
        t_first = nearest_occluder(origin64, dirs, pixels[cand], sub_ids, options.radius, neighbours, m,
                                   split_sub, topo.host_keys, cand,
                                   np.ascontiguousarray(inferred, dtype=np.float64), faces64)
    else:
        ray, tri = _window_pairs(sub_ids, pixels[cand], options.radius, neighbours, modulo=m, split=split_sub)
        keys = cand[ray] * m + tri
        pos = np.minimum(np.searchsorted(topo.host_keys, keys), len(topo.host_keys) - 1)
        other = topo.host_keys[pos] != keys
        ray, tri = ray[other], tri[other]
        t_occ = intersect_pairs(origin, dirs[ray], inferred, faces, tri)[0]
        _, t_first = _first_per_ray(ray, t_occ, len(cand))
    front = in_front(t_first, options)
    cand, dirs = cand[front], dirs[front]
    t_body = np.full(len(cand), np.inf)
    if body is not None:
        t_body = nearest_body_hit(camera, body_positions, body[1].faces, X[cand], compiled=compiled)
        past = ~(t_body < 1)
        cand, dirs, t_body = cand[past], dirs[past], t_body[past]
    visible = np.zeros(n, bool)
    visible[cand] = True
    tri_hit = np.full(n, -1, np.int64)
    bary = np.zeros((n, 3))
    back = np.zeros(n, bool)
    if compiled:
        tri_hit[cand], bary[cand], back[cand] = first_hits(
            origin64, dirs, pixels[cand], gt_ids, options.radius, neighbours,
            np.ascontiguousarray(gt, dtype=np.float64), faces64, m, t_body, topo.chart[cand], topo.gt_chart,
            topo.uv[cand], np.ascontiguousarray(topo.uv[:len(gt)]), topo.host_keys, cand)
        from_inside = compiled_seen_from_inside(np.ascontiguousarray(X, dtype=np.float64), topo.faces, origin64)
    else:
        ray, tri = _window_pairs(gt_ids, pixels[cand], options.radius, neighbours, split=split_base)
        ray, tri = _with_hosts(ray, tri, cand, topo.host_keys, m)
        tri_hit[cand], bary[cand], back[cand] = choose_hits(origin, dirs, gt, faces, ray, tri, topo.chart[cand],
                                                            topo.gt_chart, topo.uv[cand], topo.uv[:len(gt)],
                                                            t_body=t_body)
        from_inside = seen_from_inside(X, topo.faces, origin)
    return Hits(visible=visible, tri=tri_hit, bary=bary, back=back, from_inside=from_inside)
