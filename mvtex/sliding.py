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

`slide_pose` does one (pose, camera); `mvtex.slide_jobs.slide_dataset` streams a whole
dataset into a texcoord set (DESIGN §4). Rasterization goes through `mvtex.raster` with a
`GLContext` the caller passes.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

import numpy as np

from .camera import Camera
from .extrapolate import METHODS, FillSystem, fill
from .mesh import Subdivision, edges, extension_matrix, face_neighbours, subdivide, uv_charts, weld_groups

if TYPE_CHECKING:
    from .raster import GLContext


@dataclass(frozen=True)
class SlideOptions:
    """Options of texture sliding; `slide_dataset` records them in texcoords.json.

    Attributes:
        subdiv: levels of midpoint subdivision of the inferred mesh (0, 1, 2).
        fill: how unassigned vertices are filled: "harmonic" or "fmm" (`mvtex.extrapolate`).
        max_displacement: unassign vertices with ‖d‖ above this (uv units); None = no limit.
        depth_tolerance: relative tolerance of the vertex depth test: the vertex is hidden
            when some inferred surface hits its ray before (1 - tol) times its distance.
        break_ratio: an edge whose two assigned ends have ‖ΔT_N‖ > break_ratio ‖ΔT_G‖ joins
            geodesically far regions; its end with larger ‖d‖ is unassigned. None: no edge
            breaking (the paper's plain method).
        radius: candidate window half-size in pixels around a vertex's projection (1 = 3x3).
        cross_chart: keep hits on another UV chart than the vertex's own (near a seam the
            vertex then shows the right material, but in the other chart's coordinates, so
            d jumps and triangles mixing both frames interpolate garbage). The default
            unassigns them and fills: d stays a within-chart displacement (what a network
            learns and triangulation inverts).
    """

    subdiv: int = 1
    fill: str = "harmonic"
    max_displacement: float | None = None
    depth_tolerance: float = 1e-3
    break_ratio: float | None = None
    radius: int = 1
    cross_chart: bool = False

    def __post_init__(self) -> None:
        if int(self.subdiv) != self.subdiv or not 0 <= self.subdiv <= 4:
            raise ValueError(f"subdiv must be an integer in [0, 4], got {self.subdiv!r}")
        if self.fill not in METHODS:
            raise ValueError(f"fill must be one of {', '.join(METHODS)}, got {self.fill!r}")
        if self.max_displacement is not None and not self.max_displacement > 0:
            raise ValueError(f"max_displacement must be positive or None, got {self.max_displacement!r}")
        if not 0 <= self.depth_tolerance < 1:
            raise ValueError(f"depth_tolerance must be in [0, 1), got {self.depth_tolerance!r}")
        if self.break_ratio is not None and not self.break_ratio > 1:
            raise ValueError(f"break_ratio must be > 1, got {self.break_ratio!r}")
        if int(self.radius) != self.radius or not 0 <= self.radius <= 4:
            raise ValueError(f"radius must be an integer in [0, 4], got {self.radius!r}")

    def to_json(self) -> dict:
        return asdict(self)


# -- topology shared by every pose ----------------------------------------------------------

@dataclass(frozen=True)
class SlideTopology:
    """Everything about the mesh that does not change with the pose, computed once.

    Attributes:
        subdivision: the midpoint subdivision of the inferred mesh.
        faces: (m',3) int64 subdivided faces. uv: (n',2) float64 T_G on the subdivided mesh.
        edges: (e,2) int64 unique edges of the subdivided mesh.
        chart: (n',) int64 UV chart (connected component of the unwelded mesh) per vertex.
        gt_chart: (m,) int64 chart of each base (gt) face.
        groups: (n',) int64 fill groups: seam copies whose charts agree across the seam
            share a group (solved as one vertex by the fill), others are their own group.
        levels: faces of each subdivision level, levels[0] = base faces, levels[-1] = faces.
        extend: (n',n) sparse matrix, base values -> subdivided values (midpoints).
        host_keys: sorted int64 keys v * m + f for every subdivided vertex v lying on base
            face f (such a face passes through v and can never hide it).
        fill_system: `extrapolate.FillSystem` on the reference shape (harmonic fill).
        reference: (n,3) float64 reference shape (`dataset.reference_shape`): the material
            coordinates in which edge breaking measures how far apart two hits are on the cloth.
        reference_sub: (n',3) the same on the subdivided mesh.
        edge_reference_length: (e,) float64 length of each of `edges` in `reference_sub`.
        face_neighbours: (m,3) int64 base faces across each edge of each base face (-1 on
            a boundary); candidates include them, for thin (sub-pixel) triangles at fold
            contours that cover the ray but no pixel centre.
    """

    subdivision: Subdivision
    faces: np.ndarray
    uv: np.ndarray
    edges: np.ndarray
    chart: np.ndarray
    gt_chart: np.ndarray
    groups: np.ndarray
    levels: tuple
    extend: object
    host_keys: np.ndarray
    fill_system: object
    reference: np.ndarray
    reference_sub: np.ndarray
    edge_reference_length: np.ndarray
    face_neighbours: np.ndarray

    def positions(self, base: np.ndarray) -> np.ndarray:
        """Base positions (n,3) -> (n',3) float64 on the subdivided mesh."""
        return np.asarray(self.extend @ np.asarray(base, dtype=np.float64))


def _uv_jacobians(positions: np.ndarray, faces: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Per-vertex (n,2,3) mean over incident faces of the affine map 3-D tangent -> uv."""
    p = positions[faces]
    t = uv[faces]
    e = np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]], axis=2)  # (m,3,2)
    du = np.stack([t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]], axis=2)  # (m,2,2)
    # J = du @ pinv(e); pinv(e) = (e^T e)^-1 e^T
    gram = np.einsum("mki,mkj->mij", e, e)
    det = gram[:, 0, 0] * gram[:, 1, 1] - gram[:, 0, 1] ** 2
    ok = np.abs(det) > 1e-30
    inv = np.zeros_like(gram)
    inv[ok, 0, 0] = gram[ok, 1, 1] / det[ok]
    inv[ok, 1, 1] = gram[ok, 0, 0] / det[ok]
    inv[ok, 0, 1] = inv[ok, 1, 0] = -gram[ok, 0, 1] / det[ok]
    jac = np.einsum("mij,mjk,mlk->mil", du, inv, e)  # (m,2,3)
    acc = np.zeros((len(positions), 2, 3))
    cnt = np.zeros(len(positions))
    for k in range(3):
        np.add.at(acc, faces[:, k], jac)
        np.add.at(cnt, faces[:, k], 1.0)
    return acc / np.maximum(cnt, 1)[:, None, None]


def build_topology(faces: np.ndarray, uv: np.ndarray, reference: np.ndarray, subdiv: int) -> SlideTopology:
    """Precompute the pose-independent parts of texture sliding.

    Args:
        faces: (m,3) int base faces. uv: (n,2) T_G.
        reference: (n,3) the reference shape (`mvtex.dataset.reference_shape`): finds seam
            copies, checks whether the two charts at a seam have the same uv orientation
            there, carries the fill's Laplacian and measures edge breaking.
        subdiv: subdivision levels.
    """
    faces = np.asarray(faces, dtype=np.int64)
    n = len(uv)
    sub = subdivide(faces, n, subdiv)
    sub_faces = sub.faces.astype(np.int64)
    extend = extension_matrix(sub.parent, n)
    uv_sub = extend @ np.asarray(uv, np.float64)
    ref_sub = extend @ np.asarray(reference, np.float64)
    base_chart = uv_charts(faces, n)
    chart = (extend @ base_chart.astype(np.float64)).round().astype(np.int64)
    groups = weld_groups(ref_sub)
    seam = np.flatnonzero(groups != np.arange(len(groups)))
    if len(seam):
        # Join a seam copy with its group's first vertex only where the two charts map the
        # surface to uv the same way (a translation across the seam): only then is one
        # displacement right for both. Mirrored or rotated charts stay apart.
        jac = _uv_jacobians(ref_sub, sub_faces, uv_sub)
        first = groups[seam]
        diff = np.linalg.norm((jac[seam] - jac[first]).reshape(len(seam), -1), axis=1)
        scale = np.linalg.norm(jac[first].reshape(len(seam), -1), axis=1)
        apart = ~(diff <= 0.25 * scale)
        groups = groups.copy()
        groups[seam[apart]] = seam[apart]
    levels = tuple(subdivide(faces, n, k).faces.astype(np.int64) for k in range(subdiv)) + (sub_faces,)
    m = len(faces)
    base_face = np.arange(len(sub_faces)) % m  # child k*m_prev + f keeps f modulo m
    host_keys = np.unique((sub_faces * m + base_face[:, None]).ravel())
    groups = groups.astype(np.int64)
    sub_edges = edges(sub_faces)
    return SlideTopology(subdivision=sub, faces=sub_faces, uv=uv_sub, edges=sub_edges,
                         chart=chart, gt_chart=base_chart[faces[:, 0]], groups=groups,
                         levels=levels, extend=extend, host_keys=host_keys,
                         fill_system=FillSystem(sub_faces, ref_sub, groups),
                         reference=np.asarray(reference, np.float64), reference_sub=ref_sub,
                         edge_reference_length=np.linalg.norm(ref_sub[sub_edges[:, 0]] - ref_sub[sub_edges[:, 1]],
                                                              axis=1),
                         face_neighbours=face_neighbours(faces))


# -- exact ray / triangle tests ---------------------------------------------------------------

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
                  neighbours: np.ndarray | None = None, modulo: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Distinct triangle ids in the (2r+1)² window around each pixel (and their edge
    neighbours if given), as (ray, tri) pairs sorted by ray. With `modulo`, the raster's
    ids (>= 0) are taken modulo it first (subdivided face ids -> base face ids)."""
    H, W = tri_id.shape
    col = np.rint(pixels[:, 0]).astype(np.int64)
    row = np.rint(pixels[:, 1]).astype(np.int64)
    off = np.arange(-radius, radius + 1)
    rr = np.clip(row[:, None, None] + off[None, :, None], 0, H - 1)
    cc = np.clip(col[:, None, None] + off[None, None, :], 0, W - 1)
    ids = tri_id[rr, cc].reshape(len(pixels), -1)
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


# -- one (pose, camera) -----------------------------------------------------------------------

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
    from .mesh import vertex_normals

    return np.einsum("ij,ij->i", vertex_normals(X, faces), X - origin) > 0


def choose_hits(origin: np.ndarray, dirs: np.ndarray, gt: np.ndarray, gt_faces: np.ndarray, ray: np.ndarray,
                tri: np.ndarray, vert_chart: np.ndarray, gt_chart: np.ndarray, vert_uv: np.ndarray | None = None,
                gt_uv: np.ndarray | None = None):
    """Nearest hit per ray among its candidate (ray, tri) pairs. Exact ties (a ray through
    a gt vertex or edge) prefer a triangle of the vertex's own chart, then one facing the
    camera, then (given `vert_uv` (k,2) and `gt_uv` (n,2)) the one whose uv at the hit is
    nearest the vertex's own T_G: where a chart meets itself along a seam, both sides name
    the same material and the vertex keeps its own side's coordinates.
    Returns tri (k,) (-1 = no hit), bary (k,3), back (k,) bool."""
    k = len(dirs)
    t, b1, b2, facing = intersect_pairs(origin, dirs[ray], gt, gt_faces, tri)
    _, t_min = _first_per_ray(ray, t, k)
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


def find_hits_raster(ctx: GLContext, gt: np.ndarray, inferred: np.ndarray, faces: np.ndarray, X: np.ndarray,
                     topo: SlideTopology, camera: Camera, options: SlideOptions, *, compiled: bool = True) -> Hits:
    """Visibility and first gt hits by rasterization + exact candidate intersection.

    Args:
        ctx: the GL context.
        gt, inferred: (n,3) float64 base positions. faces: (m,3) base faces.
        X: (n',3) float64 subdivided inferred positions.
        compiled: search the candidates with the compiled kernels of `mvtex.hitsearch`
            (the default); False runs the NumPy formulation (`_window_pairs`,
            `intersect_pairs`, `choose_hits`), which gives the same answer, slower.
    """
    from .raster import rasterize_pair

    n = len(X)
    m = len(faces)
    origin = camera.center
    pixels, z = camera.project(X)
    gt_pixels = camera.project(gt)[0]
    # Ids of the subdivided inferred faces (they give rule 1 directly); the base face of
    # subdivided face k is k % m (children keep their parent modulo m). Both corners sets
    # bound the read-back region (the inferred base vertices are among X's first n).
    gt_ids, sub_ids = rasterize_pair(ctx, gt, inferred, faces, camera, levels=len(topo.levels) - 1,
                                     pixels=np.concatenate([gt_pixels, pixels]))
    # Rule 1 (the paper's): an incident (subdivided) triangle owns at least one pixel.
    covered = sub_ids[sub_ids >= 0]
    owned = np.zeros(len(topo.faces), bool)
    owned[covered] = True
    touched = np.zeros(n, bool)
    touched[topo.faces[owned].ravel()] = True
    cand = np.flatnonzero(touched & camera.in_image(pixels, z))
    # Rule 2: nothing of the inferred mesh in front of the vertex along its ray (t = 1 at the
    # vertex). Candidate occluders: the base inferred triangles drawn around its projection
    # (the same surface as their subdivided children).
    dirs = X[cand] - origin
    if compiled:
        from .hitsearch import first_hits, nearest_occluder
        from .hitsearch import seen_from_inside as compiled_seen_from_inside

        faces64 = np.ascontiguousarray(faces, dtype=np.int64)
        origin64 = np.ascontiguousarray(origin, dtype=np.float64)
        t_first = nearest_occluder(origin64, dirs, pixels[cand], sub_ids, options.radius, topo.face_neighbours, m,
                                   topo.host_keys, cand, np.ascontiguousarray(inferred, dtype=np.float64), faces64)
    else:
        ray, tri = _window_pairs(sub_ids, pixels[cand], options.radius, topo.face_neighbours, modulo=m)
        keys = cand[ray] * len(faces) + tri
        pos = np.minimum(np.searchsorted(topo.host_keys, keys), len(topo.host_keys) - 1)
        other = topo.host_keys[pos] != keys
        ray, tri = ray[other], tri[other]
        t_occ = intersect_pairs(origin, dirs[ray], inferred, faces, tri)[0]
        _, t_first = _first_per_ray(ray, t_occ, len(cand))
    front = t_first >= 1 - options.depth_tolerance
    cand, dirs = cand[front], dirs[front]
    visible = np.zeros(n, bool)
    visible[cand] = True
    tri_hit = np.full(n, -1, np.int64)
    bary = np.zeros((n, 3))
    back = np.zeros(n, bool)
    if compiled:
        tri_hit[cand], bary[cand], back[cand] = first_hits(
            origin64, dirs, pixels[cand], gt_ids, options.radius, topo.face_neighbours,
            np.ascontiguousarray(gt, dtype=np.float64), faces64, topo.chart[cand], topo.gt_chart, topo.uv[cand],
            np.ascontiguousarray(topo.uv[:len(gt)]))
        from_inside = compiled_seen_from_inside(np.ascontiguousarray(X, dtype=np.float64), topo.faces, origin64)
    else:
        ray, tri = _window_pairs(gt_ids, pixels[cand], options.radius, topo.face_neighbours)
        tri_hit[cand], bary[cand], back[cand] = choose_hits(origin, dirs, gt, faces, ray, tri, topo.chart[cand],
                                                            topo.gt_chart, topo.uv[cand], topo.uv[:len(gt)])
        from_inside = seen_from_inside(X, topo.faces, origin)
    return Hits(visible=visible, tri=tri_hit, bary=bary, back=back, from_inside=from_inside)


def displacement_from_hits(hits: Hits, gt_faces: np.ndarray, uv: np.ndarray, X: np.ndarray, topo: SlideTopology,
                           options: SlideOptions) -> tuple[np.ndarray, np.ndarray]:
    """Steps 4-6 from the hits: T_N, d, rejection rules, fill. Shared by every hit search.

    Returns:
        d (n',2) float32 (filled everywhere) and assigned (n',) bool, as `slide_pose`.
    """
    n = len(X)
    found = hits.tri >= 0
    t_n = np.zeros((n, 2))
    f = gt_faces[hits.tri[found]]
    t_n[found] = np.einsum("kj,kjc->kc", hits.bary[found], np.asarray(uv, np.float64)[f])
    d = t_n - topo.uv
    # A hit on the inside of the gt garment (back-facing) mixes inside and outside material
    # [Appendix A.1] — unless the inferred vertex is seen from the inside as well (a view
    # into the collar or waist): then inside meets inside and the hit is the right one.
    assigned = found & (~hits.back | hits.from_inside)
    if not options.cross_chart:
        assigned[found] &= topo.gt_chart[hits.tri[found]] == topo.chart[found]
    # Edges joining geodesically far regions [Appendix A.1]: the two hits lie much farther
    # apart on the cloth than the edge's ends. Distances are measured in the reference
    # (rest) shape, which is T_N vs T_G within a chart but stays right across UV seams,
    # where uv jumps although the material is adjacent.
    if options.break_ratio is not None:
        e = topo.edges
        both = assigned[e[:, 0]] & assigned[e[:, 1]]
        ee = e[both]
        m_n = np.zeros((n, 3))
        m_n[found] = np.einsum("kj,kjc->kc", hits.bary[found], topo.reference[f])
        dmn = np.linalg.norm(m_n[ee[:, 0]] - m_n[ee[:, 1]], axis=1)
        broken = ee[dmn > options.break_ratio * topo.edge_reference_length[both]]
        if len(broken):
            norm = np.linalg.norm(d, axis=1)
            worse = np.where(norm[broken[:, 0]] >= norm[broken[:, 1]], broken[:, 0], broken[:, 1])
            assigned[worse] = False
    if options.max_displacement is not None:
        assigned &= np.linalg.norm(d, axis=1) <= options.max_displacement
    d[~assigned] = 0.0
    d = d.astype(np.float32)
    d = fill(topo.faces, X, d, assigned, options.fill, topo.groups,
             system=topo.fill_system if options.fill == "harmonic" else None)
    return d.astype(np.float32), assigned


def slide_pose(gt_positions: np.ndarray, inferred_positions: np.ndarray, faces: np.ndarray, uv: np.ndarray,
               camera: Camera, subdivision: Subdivision, options: SlideOptions, *,
               topology: SlideTopology | None = None, ctx: GLContext | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Texture sliding for one pose and one camera (DESIGN §5 steps 1-6).

    Args:
        gt_positions: (n,3) ground-truth positions X_G (not subdivided).
        inferred_positions: (n,3) inferred positions X_N.
        faces: (m,3) int base faces (CCW seen from outside). uv: (n,2) T_G.
        camera: pinhole camera (zero distortion).
        subdivision: `mesh.subdivide(faces, n, options.subdiv)`.
        options: SlideOptions.
        topology: `build_topology(...)` for this mesh (computed here with these gt
            positions as the reference shape if None; pass it when sliding many poses).
        ctx: the GL context (one is created, and released, for this call if None).

    Returns:
        d: (n',2) float32 displacement T_N - T_G on the subdivided mesh, filled everywhere.
        assigned: (n',) bool, True where d came from the ray.
    """
    gt = np.asarray(gt_positions, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if topology is None:
        levels = int(round(np.log(len(subdivision.faces) / max(len(faces), 1)) / np.log(4)))
        topology = build_topology(faces, uv, gt, levels)
    inferred = np.asarray(inferred_positions, dtype=np.float64)
    X = topology.positions(inferred)
    if ctx is None:
        from .raster import GLContext

        with GLContext() as own:
            hits = find_hits_raster(own, gt, inferred, faces, X, topology, camera, options)
    else:
        hits = find_hits_raster(ctx, gt, inferred, faces, X, topology, camera, options)
    return displacement_from_hits(hits, faces, uv, X, topology, options)
