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

`slide_pose` does one (pose, camera); `slide_dataset` streams a whole dataset into a
texcoord set (DESIGN §4), resumable, on local processes or a Dask cluster.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from .camera import Camera, Rig
from .errors import InputError
from .extrapolate import METHODS, FillSystem, fill
from .mesh import Subdivision, apply_parent, edges, subdivide, weld_groups


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
            geodesically far regions; its end with larger ‖d‖ is unassigned.
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
    break_ratio: float = 4.0
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
        if not self.break_ratio > 1:
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
        reference: (n,3) float64 reference (rest) positions, the material coordinates in
            which edge breaking measures how far apart two hits are on the cloth.
        reference_sub: (n',3) the same on the subdivided mesh.
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
    face_neighbours: np.ndarray

    def positions(self, base: np.ndarray) -> np.ndarray:
        """Base positions (n,3) -> (n',3) float64 on the subdivided mesh."""
        return np.asarray(self.extend @ np.asarray(base, dtype=np.float64))


def _charts(faces: np.ndarray, n: int) -> np.ndarray:
    import scipy.sparse as sp
    import scipy.sparse.csgraph as csgraph

    f = np.asarray(faces, dtype=np.int64)
    a = sp.coo_matrix((np.ones(2 * len(f)), (f[:, [0, 1]].ravel(), f[:, [1, 2]].ravel())), shape=(n, n))
    return csgraph.connected_components(a, directed=False)[1].astype(np.int64)


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
        reference: (n,3) positions of any pose (or the rest shape): finds seam copies and
            checks whether the two charts at a seam have the same uv orientation there.
        subdiv: subdivision levels.
    """
    faces = np.asarray(faces, dtype=np.int64)
    n = len(uv)
    sub = subdivide(faces, n, subdiv)
    sub_faces = sub.faces.astype(np.int64)
    uv_sub = apply_parent(np.asarray(uv, np.float64), sub.parent)
    ref_sub = apply_parent(np.asarray(reference, np.float64), sub.parent)
    base_chart = _charts(faces, n)
    chart = apply_parent(base_chart[:, None].astype(np.float64), sub.parent)[:, 0].round().astype(np.int64)
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
    return SlideTopology(subdivision=sub, faces=sub_faces, uv=uv_sub, edges=edges(sub_faces),
                         chart=chart, gt_chart=base_chart[faces[:, 0]], groups=groups,
                         levels=levels, extend=_extension_matrix(sub.parent, n), host_keys=host_keys,
                         fill_system=FillSystem(sub_faces, ref_sub, groups),
                         reference=np.asarray(reference, np.float64), reference_sub=ref_sub,
                         face_neighbours=_face_neighbours(faces))


def _face_neighbours(faces: np.ndarray) -> np.ndarray:
    """(m,3) face across edge (k, k+1) of each face; -1 where none (first match on
    non-manifold edges)."""
    m = len(faces)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    key = np.sort(e, axis=1)
    key = key[:, 0] * (faces.max() + 1) + key[:, 1]
    slot = np.arange(3 * m)
    order = np.argsort(key, kind="stable")
    ks = key[order]
    out = np.full(3 * m, -1, np.int64)
    same = ks[1:] == ks[:-1]
    a, b = order[:-1][same], order[1:][same]
    out[a] = b % m
    out[b] = a % m
    return out.reshape(3, m).T


def _extension_matrix(parent: np.ndarray, n: int):
    """(n',n) sparse matrix E with E @ base == apply_parent(base, parent)."""
    import scipy.sparse as sp

    E = sp.identity(n, format="csr")
    start = n
    while start < len(parent):
        # One level at a time: the vertices whose parents all precede `start`.
        stop = start + int(np.argmax(np.r_[parent[start:].max(axis=1) >= start, True]))
        p = parent[start:stop]
        E = sp.vstack([E, 0.5 * (E[p[:, 0]] + E[p[:, 1]])]).tocsr()
        start = stop
    return E


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


# -- rasterization of both meshes in one pass -------------------------------------------------

_SUBFACE_FRAG = """
#version 330
// Triangle id + 1 (0 = background). With levels > 0 the id is that of the midpoint-
// subdivided child face containing the pixel centre, found from the perspective-correct
// barycentrics in the drawn (base) face: children of face f are k * m + f for corner
// children k = 0, 1, 2 (barycentric of corner k above 1/2) and the centre child k = 3
// (`mvtex.mesh.subdivide`'s order); the barycentrics are then mapped into the child.
uniform int num_faces;
uniform int levels;
in vec3 v_bary;
in float v_z;
layout(location = 0) out int out_id;
void main() {
    vec3 b = v_bary;
    int f = gl_PrimitiveID;
    int m = num_faces;
    for (int level = 0; level < levels; ++level) {
        int k;
        if (b.x > 0.5) { k = 0; b = vec3(2.0 * b.x - 1.0, 2.0 * b.y, 2.0 * b.z); }
        else if (b.y > 0.5) { k = 1; b = vec3(2.0 * b.x, 2.0 * b.y - 1.0, 2.0 * b.z); }
        else if (b.z > 0.5) { k = 2; b = vec3(2.0 * b.x, 2.0 * b.y, 2.0 * b.z - 1.0); }
        else { k = 3; b = vec3(1.0 - 2.0 * b.z, 1.0 - 2.0 * b.x, 1.0 - 2.0 * b.y); }
        f = k * m + f;
        m = 4 * m;
    }
    out_id = f + 1;
}
"""


class PairRaster:
    """Triangle ids of two meshes with the same base faces (gt and inferred) from one
    camera, drawn side by side in one framebuffer: one upload, one readback.

    The second mesh can report ids of its midpoint subdivision (`levels`) while only its
    base faces are drawn: the child face of each pixel follows from the pixel's
    barycentrics in the base face (midpoint subdivision does not move the surface, and
    barycentrics are perspective-correct). That equals a raster of the subdivided mesh up
    to pixel centres exactly on a child edge, at the cost of a base raster (llvmpipe's
    cost grows with the triangle count). Projection and ids follow `mvtex.raster`
    (`rasterize(..., attributes=False)`): row r, column c is OpenCV pixel (u=c, v=r).
    """

    def __init__(self, faces: np.ndarray, num_vertices: int, levels: int = 0):
        from .raster import _shader_source, gl_context

        self.ctx = gl_context()
        self.prog = self.ctx.program(vertex_shader=_shader_source("raster.vert.glsl"), fragment_shader=_SUBFACE_FRAG)
        self.n = int(num_vertices)
        self.m = len(faces)
        self.levels = int(levels)
        f = np.asarray(faces, dtype=np.int32)
        self.faces = f
        self.ibo = self.ctx.buffer(f.tobytes())
        self.vbo = self.ctx.buffer(reserve=self.n * 12)
        self.vao = self.ctx.vertex_array(self.prog, [(self.vbo, "3f", "in_cam")], index_buffer=self.ibo,
                                         index_element_size=4)
        # The second mesh de-indexed: each corner carries a one-hot barycentric.
        self.vbo2 = self.ctx.buffer(reserve=3 * self.m * 12)
        self.bary = self.ctx.buffer(np.tile(np.eye(3, dtype=np.float32), (self.m, 1)).tobytes())
        self.vao2 = self.ctx.vertex_array(self.prog, [(self.vbo2, "3f", "in_cam"), (self.bary, "3f", "in_bary")])
        self._targets: dict = {}

    def _target(self, width: int, height: int):
        key = (width, height)
        if key not in self._targets:
            ids = self.ctx.texture((2 * width, height), 1, dtype="i4")
            depth = self.ctx.depth_renderbuffer((2 * width, height))
            self._targets[key] = (self.ctx.framebuffer(color_attachments=[ids], depth_attachment=depth), ids, depth)
        return self._targets[key][0]

    def __call__(self, first: np.ndarray, second: np.ndarray, camera: Camera,
                 pixels: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(H,W) int32 tri_id of `first` (base faces) and of `second` (faces of its
        `levels`-times subdivision), positions (n,3) world; -1 = background.

        `pixels`, if given, (k,2) projections of every vertex of both meshes: they bound the
        region read back.
        """
        import moderngl

        from .raster import _check_renderable, clip_from_camera, depth_range

        _check_renderable(camera)
        cam = camera.to_camera(np.concatenate([first, second])).astype(np.float32)
        near, far = depth_range(cam)
        W, H = camera.width, camera.height
        self.prog["clip_from_cam"].write(clip_from_camera(camera, near, far).T.astype("f4").tobytes())
        self.vbo.write(cam[:self.n].tobytes())
        self.vbo2.write(cam[self.n:][self.faces].tobytes())
        fbo = self._target(W, H)
        fbo.use()
        fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        self.ctx.disable(moderngl.CULL_FACE)
        self.ctx.enable(moderngl.DEPTH_TEST)
        # The viewport clips in clip space: nothing of one mesh can spill into the other half.
        self.prog["num_faces"].value = self.m
        self.ctx.viewport = (0, 0, W, H)
        self.prog["levels"].value = 0
        self.vao.render(moderngl.TRIANGLES, vertices=3 * self.m)
        self.ctx.viewport = (W, 0, W, H)
        self.prog["levels"].value = self.levels
        self.vao2.render(moderngl.TRIANGLES, vertices=3 * self.m)
        # A triangle covers only pixel centres inside the box of its projected corners, so
        # the box of all projections (one pixel margin) holds every id; with a vertex
        # behind the camera the projection says nothing: read everything.
        c0, r0, c1, r1 = 0, 0, W, H
        if pixels is not None and len(pixels) and bool(np.all(cam[:, 2] > 0)):
            lo = np.floor(pixels.min(axis=0)).astype(np.int64) - 1
            hi = np.ceil(pixels.max(axis=0)).astype(np.int64) + 2
            c0, r0 = int(np.clip(lo[0], 0, W)), int(np.clip(lo[1], 0, H))
            c1, r1 = int(np.clip(hi[0], c0, W)), int(np.clip(hi[1], r0, H))
        out1 = np.full((H, W), -1, np.int32)
        out2 = np.full((H, W), -1, np.int32)
        w, h = c1 - c0, r1 - r0
        if w > 0 and h > 0:
            # GL window row y is image row v (the projection flips once), so no flip here.
            for out, x0 in ((out1, c0), (out2, W + c0)):
                data = fbo.read(attachment=0, components=1, dtype="i4", viewport=(x0, r0, w, h))
                # gl_PrimitiveID restarts at 0 on each draw call; ids are stored +1.
                out[r0:r1, c0:c1] = np.frombuffer(data, np.int32).reshape(h, w) - 1
        return out1, out2

    def release(self) -> None:
        # moderngl rebinds its last used framebuffer when it creates the next one: binding a
        # released one is GL_INVALID_OPERATION. Leave the default framebuffer bound instead.
        if any(self.ctx.fbo is fbo for fbo, _, _ in self._targets.values()):
            self.ctx.detect_framebuffer(0).use()
        for fbo, ids, depth in self._targets.values():
            fbo.release(), ids.release(), depth.release()
        self.vao.release(), self.vbo.release(), self.ibo.release()
        self.vao2.release(), self.vbo2.release(), self.bary.release()
        self.prog.release()


_RASTERS: dict = {}


def _pair_raster(faces: np.ndarray, n: int, levels: int = 0) -> PairRaster:
    key = (n, len(faces), int(levels), hashlib.sha1(np.ascontiguousarray(faces, dtype=np.int64).tobytes()).hexdigest())
    if key not in _RASTERS:
        if len(_RASTERS) > 4:
            _RASTERS.pop(next(iter(_RASTERS))).release()
        _RASTERS[key] = PairRaster(faces, n, levels)
    return _RASTERS[key]


def owned_subfaces(base_ids: np.ndarray, pixels: np.ndarray, topo: SlideTopology) -> np.ndarray:
    """Which subdivided faces own at least one pixel, from a raster of the *base* mesh.

    Midpoint subdivision does not move the surface, so a pixel of base face f belongs to
    one of its four children; perspective maps lines to lines, so the child is found in 2-D
    from the projected midpoints: outside the centre child across its edge opposite a
    midpoint means the corner child on that side. Repeated per level.

    Args:
        base_ids: (H,W) int32 tri_id of the base inferred mesh.
        pixels: (n',2) projections of the subdivided vertices.

    Returns:
        (m',) bool over the subdivided faces.
    """
    rows, cols = np.nonzero(base_ids >= 0)
    face = base_ids[rows, cols].astype(np.int64)
    p = np.stack([cols, rows], axis=1).astype(np.float64)
    for level in range(1, len(topo.levels)):
        m_prev = len(topo.levels[level - 1])
        centre = topo.levels[level][3 * m_prev + face]  # (m01, m12, m20)
        a, b, c = pixels[centre[:, 0]], pixels[centre[:, 1]], pixels[centre[:, 2]]
        # Signed areas; the centre triangle's orientation sign normalises them.
        def cross(o, q, r):
            return (q[:, 0] - o[:, 0]) * (r[:, 1] - o[:, 1]) - (q[:, 1] - o[:, 1]) * (r[:, 0] - o[:, 0])
        area = cross(a, b, c)
        sgn = np.where(area >= 0, 1.0, -1.0)
        l_m12 = cross(c, a, p) * sgn  # weight of m12: side of edge (m20, m01)
        l_m20 = cross(a, b, p) * sgn  # weight of m20: side of edge (m01, m12)
        l_m01 = cross(b, c, p) * sgn  # weight of m01: side of edge (m12, m20)
        child = np.full(len(face), 3)
        child[l_m01 < 0] = 2
        child[l_m20 < 0] = 1
        child[l_m12 < 0] = 0
        face = child * m_prev + face
    owned = np.zeros(len(topo.faces), bool)
    owned[face] = True
    return owned


# -- one (pose, camera) -----------------------------------------------------------------------

@dataclass
class Hits:
    """Result of the hit search for the subdivided inferred vertices (n').

    Attributes:
        visible: (n',) bool, the vertex passed both visibility rules.
        tri: (n',) int64 gt triangle of the first hit (-1 if none).
        bary: (n',3) float64 barycentrics of the hit in `tri`.
        back: (n',) bool, the hit triangle faces away from the camera.
        inside: (n',) bool, the inferred vertex itself is seen from the garment's inside
            (its normal faces away from the camera, e.g. looking into a collar).
    """

    visible: np.ndarray
    tri: np.ndarray
    bary: np.ndarray
    back: np.ndarray
    inside: np.ndarray


def seen_from_inside(X: np.ndarray, faces: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """(n,) bool: the area-weighted vertex normal of X (faces CCW from outside) points away
    from the camera at `origin`."""
    p = X[faces]
    fn = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    normals = np.stack([np.bincount(faces.ravel(), np.repeat(fn[:, c], 3), minlength=len(X)) for c in range(3)], 1)
    return np.einsum("ij,ij->i", normals, X - origin) > 0


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
    near = np.isfinite(t) & (t <= t_min[ray] * (1 + 1e-9))
    back = facing > 0
    other = gt_chart[tri] != vert_chart[ray]
    key = 4.0 * other + 2.0 * back
    if vert_uv is not None and gt_uv is not None:
        corners = gt_uv[gt_faces[tri]]
        w = np.stack([1 - b1 - b2, b1, b2], axis=1)
        hit_uv = np.einsum("kj,kjc->kc", np.nan_to_num(w), corners)
        key = key + np.minimum(np.linalg.norm(hit_uv - vert_uv[ray], axis=1), 1.0)
    key = np.where(near, key, np.inf)
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


def find_hits_raster(gt: np.ndarray, inferred: np.ndarray, faces: np.ndarray, X: np.ndarray, topo: SlideTopology,
                     camera: Camera, options: SlideOptions) -> Hits:
    """Visibility and first gt hits by rasterization + exact candidate intersection.

    Args:
        gt, inferred: (n,3) float64 base positions. faces: (m,3) base faces.
        X: (n',3) float64 subdivided inferred positions.
    """
    n = len(X)
    m = len(faces)
    origin = camera.center
    pixels, z = camera.project(X)
    gt_pixels = camera.project(gt)[0]
    # Ids of the subdivided inferred faces (they give rule 1 directly); the base face of
    # subdivided face k is k % m (children keep their parent modulo m). Both corners sets
    # bound the read-back region (the inferred base vertices are among X's first n).
    raster = _pair_raster(faces, len(gt), len(topo.levels) - 1)
    gt_ids, sub_ids = raster(gt, inferred, camera, np.concatenate([gt_pixels, pixels]))
    H, W = sub_ids.shape
    # Rule 1 (the paper's): an incident (subdivided) triangle owns at least one pixel.
    covered = sub_ids[sub_ids >= 0]
    owned = np.zeros(len(topo.faces), bool)
    owned[covered] = True
    touched = np.zeros(n, bool)
    touched[topo.faces[owned].ravel()] = True
    inside = (z > 0) & (pixels[:, 0] > -0.5) & (pixels[:, 0] < W - 0.5) & (pixels[:, 1] > -0.5) & (pixels[:, 1] < H - 0.5)
    cand = np.flatnonzero(touched & inside)
    # Rule 2: nothing of the inferred mesh in front of the vertex along its ray (t = 1 at the
    # vertex). Candidate occluders: the base inferred triangles drawn around its projection
    # (the same surface as their subdivided children).
    dirs = X[cand] - origin
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
    ray, tri = _window_pairs(gt_ids, pixels[cand], options.radius, topo.face_neighbours)
    tri_hit[cand], bary[cand], back[cand] = choose_hits(origin, dirs, gt, faces, ray, tri, topo.chart[cand],
                                                        topo.gt_chart, topo.uv[cand], topo.uv[:len(gt)])
    return Hits(visible=visible, tri=tri_hit, bary=bary, back=back, inside=seen_from_inside(X, topo.faces, origin))


def finish(hits: Hits, gt_faces: np.ndarray, uv: np.ndarray, X: np.ndarray, topo: SlideTopology,
           options: SlideOptions) -> tuple[np.ndarray, np.ndarray]:
    """Steps 4-6 from the hits: T_N, d, rejection rules, fill. Shared by every hit search."""
    n = len(X)
    found = hits.tri >= 0
    t_n = np.zeros((n, 2))
    f = gt_faces[hits.tri[found]]
    t_n[found] = np.einsum("kj,kjc->kc", hits.bary[found], np.asarray(uv, np.float64)[f])
    d = t_n - topo.uv
    # A hit on the inside of the gt garment (back-facing) mixes inside and outside material
    # [Appendix A.1] — unless the inferred vertex is seen from the inside as well (a view
    # into the collar or waist): then inside meets inside and the hit is the right one.
    assigned = found & (~hits.back | hits.inside)
    if not options.cross_chart:
        assigned[found] &= topo.gt_chart[hits.tri[found]] == topo.chart[found]
    # Edges joining geodesically far regions [Appendix A.1]: the two hits lie much farther
    # apart on the cloth than the edge's ends. Distances are measured in the reference
    # (rest) shape, which is T_N vs T_G within a chart but stays right across UV seams,
    # where uv jumps although the material is adjacent.
    e = topo.edges
    both = assigned[e[:, 0]] & assigned[e[:, 1]]
    ee = e[both]
    m_n = np.zeros((n, 3))
    m_n[found] = np.einsum("kj,kjc->kc", hits.bary[found], topo.reference[f])
    dmn = np.linalg.norm(m_n[ee[:, 0]] - m_n[ee[:, 1]], axis=1)
    dmg = np.linalg.norm(topo.reference_sub[ee[:, 0]] - topo.reference_sub[ee[:, 1]], axis=1)
    broken = ee[dmn > options.break_ratio * dmg]
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
               topology: SlideTopology | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Texture sliding for one pose and one camera (DESIGN §5 steps 1-6).

    Args:
        gt_positions: (n,3) ground-truth positions X_G (not subdivided).
        inferred_positions: (n,3) inferred positions X_N.
        faces: (m,3) int base faces (CCW seen from outside). uv: (n,2) T_G.
        camera: pinhole camera (zero distortion).
        subdivision: `mesh.subdivide(faces, n, options.subdiv)`.
        options: SlideOptions.
        topology: `build_topology(...)` for this mesh (computed here from the gt positions
            if None; pass it when sliding many poses).

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
    hits = find_hits_raster(gt, inferred, faces, X, topology, camera, options)
    return finish(hits, faces, uv, X, topology, options)


# -- a whole dataset ----------------------------------------------------------------------------

_CHUNK = 8  # poses per task: amortises task overhead, keeps results small (≈1 MB)
_AUTO_WORKERS = 8  # workers=None: one process per core, up to this many
_AUTO_MIN_JOBS = 256  # workers=None: fewer jobs left than this run in this process (start-up ≈ 1-2 s a worker)


def _fingerprint(*arrays: np.ndarray) -> str:
    h = hashlib.sha1()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str(a.shape).encode())
        h.update(str(a.dtype).encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]


def _rig_record(rig: Rig) -> dict:
    return {cam.name: {"width": cam.width, "height": cam.height, "K": cam.K.tolist(), "R": cam.R.tolist(),
                       "t": cam.t.tolist()} for cam in rig}


@dataclass(frozen=True)
class _Spec:
    """What a worker needs to slide chunks of poses: picklable, cached per process by key."""

    dataset: str
    rig: Rig
    options: SlideOptions
    key: str
    worker: bool = False


_STATE: dict = {}


def _single_thread_gl() -> None:
    """Let llvmpipe rasterize in the calling thread (fewer CPU cycles per draw) in a
    worker process that has no GL context yet: with one process per core its own
    rasterizer threads would only compete with the other processes."""
    from . import raster

    if raster._CONTEXT is None:
        os.environ.setdefault("LP_NUM_THREADS", "0")


def _state(spec: _Spec):
    if spec.key not in _STATE:
        from .dataset import load_dataset

        ds = load_dataset(spec.dataset, validate=False)
        reference = ds.rest if ds.rest is not None else ds.gt[0]
        topo = build_topology(ds.faces, ds.uv, reference, spec.options.subdiv)
        _STATE.clear()
        _STATE[spec.key] = (ds, topo)
    return _STATE[spec.key]


def _slide_chunk(spec: _Spec, camera: str, rows: list[int], poses: list[int]):
    """Slide poses[rows] for one camera; returns (camera, rows, d (r,n',2), assigned (r,n'))."""
    if spec.worker:
        _single_thread_gl()
    ds, topo = _state(spec)
    cam = spec.rig[camera]
    d_out = np.empty((len(rows), len(topo.uv), 2), np.float32)
    a_out = np.empty((len(rows), len(topo.uv)), bool)
    for i, row in enumerate(rows):
        k = poses[row]
        d_out[i], a_out[i] = slide_pose(ds.gt[k], ds.inferred[k], ds.faces, ds.uv, cam, topo.subdivision,
                                        spec.options, topology=topo)
    return camera, rows, d_out, a_out


def slide_dataset(dataset, rig, out: str | os.PathLike, *, poses: list[int], options: SlideOptions,
                  cameras: list[str] | None = None, workers: int | None = None, scheduler: str | None = None,
                  progress: bool = True) -> Path:
    """Texture-slide every (pose, camera) of a dataset into a texcoord set (DESIGN §4).

    Results stream into memory-mapped .npy files in ``<out>.partial/``; a per-camera done
    mask (``done.npy``) is saved after the data of every chunk is flushed, so an
    interrupted run continues where it stopped when called again with the same arguments.
    Called with different options, poses, cameras, rig or dataset (path or content), it
    discards the partial result (saying so on stderr) and starts over. When every job is
    done the directory is renamed to `out` (an older `out` is renamed aside first and
    deleted after).

    Args:
        dataset: a `Dataset` or a dataset directory.
        rig: a `Rig` or a rig path / built-in rig name.
        out: the texcoord set directory to write.
        poses: dataset pose indices (rows of the set, in this order).
        options: SlideOptions (recorded in texcoords.json as "options").
        cameras: camera names (default: every camera of the rig).
        workers: local processes (each with its own GL context); 1 = this process; None =
            up to `_AUTO_WORKERS` (one per CPU core) when at least `_AUTO_MIN_JOBS` jobs are
            left (a process takes about a second to start), else 1.
        scheduler: Dask scheduler address (overrides `workers`).
        progress: show a progress bar on stderr.

    Returns:
        Path of the finished texcoord set.
    """
    from numpy.lib.format import open_memmap
    from tqdm import tqdm

    from .camera import load_rig, resolve_rig
    from .dataset import Dataset, load_dataset
    from .io import fingerprint as content_fingerprint
    from .io import load_npy, read_json, replace_path, save_npy
    from .texcoords import write_header

    ds = dataset if isinstance(dataset, Dataset) else load_dataset(dataset)
    if not isinstance(rig, Rig):
        rig_path = resolve_rig(rig)
        rig = load_rig(rig_path)
    else:
        rig_path = None
    rig = rig.select(cameras, source=rig_path)
    poses = ds.check_poses(poses)
    out = Path(out)
    partial = out.with_name(out.name + ".partial")
    reference = ds.rest if ds.rest is not None else ds.gt[poses[0]]
    topo = build_topology(ds.faces, ds.uv, reference, options.subdiv)
    n_sub = len(topo.uv)
    record = {
        "options": options.to_json(),
        "dataset": {"path": str(Path(ds.path).resolve()), "name": ds.name, "num_poses": ds.num_poses,
                    "num_vertices": ds.num_vertices, "mesh": _fingerprint(ds.faces, ds.uv),
                    # Content, not only the path: arrays replaced in place must not be mixed.
                    "content": content_fingerprint(ds.gt, ds.inferred, ds.poses)},
        "rig": _rig_record(rig),
    }
    if partial.is_dir():
        try:
            old = read_json(partial / "texcoords.json")
        except InputError:
            old = None
        if not (isinstance(old, dict) and old.get("format") == "mvtex-texcoords"):
            raise InputError(partial, "exists and is not an unfinished mvtex slide; move it away and rerun")
        same = isinstance(old, dict) and all(old.get(k) == v for k, v in record.items()) and \
            old.get("poses") == poses and old.get("cameras") == rig.names and old.get("subdiv") == options.subdiv
        if not same:
            print(f"{partial}: an unfinished run with other settings; starting over", file=sys.stderr)
            shutil.rmtree(partial)
    if not partial.is_dir():
        tmp = partial.with_name(partial.name + ".new")
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        write_header(tmp, faces=topo.faces, uv=topo.uv, parent=topo.subdivision.parent, source="ts",
                     subdiv=options.subdiv, poses=poses, cameras=rig.names, **record)
        for cam in rig.names:
            (tmp / cam).mkdir()
            open_memmap(tmp / cam / "displacement.npy", mode="w+", dtype=np.float32, shape=(len(poses), n_sub, 2)).flush()
            open_memmap(tmp / cam / "assigned.npy", mode="w+", dtype=np.bool_, shape=(len(poses), n_sub)).flush()
            np.save(tmp / cam / "done.npy", np.zeros(len(poses), bool), allow_pickle=False)
        os.replace(tmp, partial)

    disp = {c: open_memmap(partial / c / "displacement.npy", mode="r+") for c in rig.names}
    asg = {c: open_memmap(partial / c / "assigned.npy", mode="r+") for c in rig.names}
    # A missing done mask (a run stopped while finishing) means: redo that camera.
    done = {c: np.array(load_npy(partial / c / "done.npy", mmap=False), dtype=bool)
            if (partial / c / "done.npy").is_file() else np.zeros(len(poses), bool) for c in rig.names}
    for c in rig.names:
        if disp[c].shape != (len(poses), n_sub, 2) or asg[c].shape != (len(poses), n_sub) or done[c].shape != (len(poses),):
            raise InputError(partial / c, "unfinished result has unexpected array shapes; delete it and rerun")
    tasks = []
    for c in rig.names:
        todo = np.flatnonzero(~done[c]).tolist()
        for i in range(0, len(todo), _CHUNK):
            tasks.append((c, todo[i:i + _CHUNK]))
    left = sum(len(r) for _, r in tasks)
    if workers is None:
        workers = min(_AUTO_WORKERS, os.cpu_count() or 1) if left >= _AUTO_MIN_JOBS else 1
    # Smaller tasks when they would not keep every worker busy.
    if workers > 1 and not scheduler and len(tasks) < 4 * workers:
        tasks = [(c, rows[i:i + 2]) for c, rows in tasks for i in range(0, len(rows), 2)]
    spec = _Spec(dataset=str(ds.path), rig=rig, options=options,
                 key=_fingerprint(np.frombuffer(json.dumps(record, sort_keys=True).encode(), np.uint8)),
                 worker=workers > 1 and not scheduler)
    _STATE.clear()
    _STATE[spec.key] = (ds, topo)  # this process's jobs reuse what was just built
    total = len(poses) * len(rig)
    dirty: set = set()

    def flush() -> None:
        for c in dirty:
            disp[c].flush()
            asg[c].flush()
            save_npy(partial / c / "done.npy", done[c])
        dirty.clear()

    from .parallel import map_unordered

    bar = tqdm(total=total, initial=total - sum(len(r) for _, r in tasks), desc="slide", unit="job",
               disable=not progress, file=sys.stderr)
    try:
        for cam, rows, d, a in map_unordered(_slide_chunk, [(spec, c, rows, poses) for c, rows in tasks],
                                             workers=workers, scheduler=scheduler):
            disp[cam][rows] = d
            asg[cam][rows] = a
            done[cam][rows] = True
            dirty.add(cam)
            bar.update(len(rows))
            flush()  # after every chunk: an interrupted run loses at most the chunks in flight
    finally:
        flush()
        bar.close()
    del disp, asg
    missing = [c for c in rig.names if not done[c].all()]
    if missing:  # a backend that lost tasks: never rename an incomplete set into place
        raise RuntimeError(f"{partial}: {int((~done[missing[0]]).sum())} poses of camera {missing[0]!r} were not "
                           "computed; rerun to finish them")
    # Rename the finished set in (an older `out` aside first), then drop the done masks:
    # a stop in between leaves either a resumable partial or a complete set.
    replace_path(partial, out)
    for c in rig.names:
        (out / c / "done.npy").unlink(missing_ok=True)
    return out
