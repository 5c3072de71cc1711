"""Triangle-mesh topology shared by every stage: edges, adjacency, seams, subdivision,
Laplacians, normals and edge strain.

Meshes are plain arrays: `faces` int32 (m,3) counter-clockwise seen from outside,
`uv` float32 (n,2) per vertex (UV seams are split vertices: two vertices, one position).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp
import scipy.sparse.csgraph as csgraph


def edges(faces: np.ndarray) -> np.ndarray:
    """Unique undirected edges (e,2) int64, each row sorted (i < j)."""
    f = np.asarray(faces, dtype=np.int64)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    e.sort(axis=1)
    return np.unique(e, axis=0)


def adjacency(faces: np.ndarray, n: int) -> sp.csr_matrix:
    """Symmetric (n,n) vertex adjacency with unit weights."""
    e = edges(faces)
    a = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    return (a + a.T).tocsr()


def face_neighbours(faces: np.ndarray) -> np.ndarray:
    """(m,3) int64: the face across edge (k, k+1) of each face; -1 on a boundary (the
    first match on a non-manifold edge)."""
    faces = np.asarray(faces, dtype=np.int64)
    m = len(faces)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    key = np.sort(e, axis=1)
    key = key[:, 0] * (faces.max() + 1) + key[:, 1]
    order = np.argsort(key, kind="stable")
    ks = key[order]
    out = np.full(3 * m, -1, np.int64)
    same = ks[1:] == ks[:-1]
    a, b = order[:-1][same], order[1:][same]
    out[a] = b % m
    out[b] = a % m
    return out.reshape(3, m).T


def weld_groups(positions: np.ndarray, decimals: int = 7) -> np.ndarray:
    """For each vertex, the index of the first vertex at the same position (n,) int64.

    Seam copies (split vertices for UV charts) share a group; everything else maps to itself.
    """
    key = np.round(np.asarray(positions, dtype=np.float64), decimals)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    return first[inverse.reshape(-1)]


def welded_adjacency(faces: np.ndarray, groups: np.ndarray) -> sp.csr_matrix:
    """Adjacency of the mesh with seam copies joined: copies share their neighbours.

    Returns (n,n) over the original vertices: vertex i is linked to every vertex whose
    group neighbours i's group, and to its own seam copies.
    """
    n = len(groups)
    g = np.asarray(groups)
    adj_groups = adjacency(g[np.asarray(faces)], n)
    member = sp.coo_matrix((np.ones(n), (np.arange(n), g)), shape=(n, n)).tocsr()  # vertex -> group
    linked = member @ (adj_groups + sp.identity(n, format="csr")) @ member.T
    linked = (linked > 0).astype(np.float64).tolil()
    linked.setdiag(0)
    return linked.tocsr()


def uniform_laplacian(adj: sp.csr_matrix) -> sp.csr_matrix:
    """Graph Laplacian L = D - A of an adjacency matrix."""
    deg = np.asarray(adj.sum(axis=1)).ravel()
    return (sp.diags(deg) - adj).tocsr()


def face_normals(positions: np.ndarray, faces: np.ndarray, normalize: bool = True) -> np.ndarray:
    """(m,3) face normals (area-weighted when normalize=False)."""
    p = np.asarray(positions, dtype=np.float64)
    f = np.asarray(faces)
    n = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])
    if normalize:
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    return n


def vertex_normals(positions: np.ndarray, faces: np.ndarray, groups: np.ndarray | None = None) -> np.ndarray:
    """(n,3) unit area-weighted vertex normals; seam copies (same `groups`) share one normal."""
    p = np.asarray(positions, dtype=np.float64)
    f = np.asarray(faces)
    fn = face_normals(p, f, normalize=False)
    corners = f.ravel()
    acc = np.stack([np.bincount(corners, np.repeat(fn[:, c], 3), minlength=len(p)) for c in range(3)], axis=1)
    if groups is not None:
        pooled = np.zeros_like(acc)
        np.add.at(pooled, groups, acc)
        acc = pooled[groups]
    return acc / np.maximum(np.linalg.norm(acc, axis=1, keepdims=True), 1e-300)


def edge_strain(positions: np.ndarray, rest: np.ndarray, edge_list: np.ndarray) -> np.ndarray:
    """Per-edge strain len/rest_len - 1, (e,) float64 (negative = compression).

    `positions` may be (n,3) or (K,n,3).
    """
    p = np.asarray(positions, dtype=np.float64)
    r = np.asarray(rest, dtype=np.float64)
    rest_len = np.linalg.norm(r[edge_list[:, 1]] - r[edge_list[:, 0]], axis=-1)
    length = np.linalg.norm(p[..., edge_list[:, 1], :] - p[..., edge_list[:, 0], :], axis=-1)
    return length / np.maximum(rest_len, 1e-300) - 1.0


def vertex_strain_energy(positions: np.ndarray, rest: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Signed per-vertex strain (n,) float64: mean strain of incident edges.

    Negative = compression, positive = extension (the paper's blue/red energy pictures).
    """
    e = edges(faces)
    s = edge_strain(positions, rest, e)
    n = len(rest)
    acc = np.zeros(n)
    cnt = np.zeros(n)
    for k in range(2):
        np.add.at(acc, e[:, k], s)
        np.add.at(cnt, e[:, k], 1.0)
    return acc / np.maximum(cnt, 1)


def rms_distance(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float | None:
    """Root mean square of the point distances ‖a - b‖ (meters for positions).

    Args:
        a, b: (..., n, 3) points (any leading pose axes). mask: optional (n,) bool selecting
            vertices.

    Returns:
        float, or None when nothing is selected.
    """
    squared = np.sum((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2, axis=-1)
    if mask is not None:
        squared = squared[..., np.asarray(mask, bool)]
    return float(np.sqrt(np.mean(squared))) if squared.size else None


@dataclass(frozen=True)
class Subdivision:
    """A midpoint subdivision of a mesh.

    Attributes:
        faces: (m',3) int32 faces of the subdivided mesh (4^levels * m).
        parent: (n',2) int32; the original n vertices come first with parent[i] = (i, i);
            every later vertex is the midpoint of vertices parent[j] (which precede it).
    """

    faces: np.ndarray
    parent: np.ndarray

    @property
    def num_vertices(self) -> int:
        return len(self.parent)

    @cached_property
    def extension(self) -> sp.csr_matrix:
        """(n',n) sparse matrix E: E @ base values = subdivided values (`extension_matrix`)."""
        return extension_matrix(self.parent)

    def apply(self, values: np.ndarray) -> np.ndarray:
        """Extend per-vertex values (..., n, C) to the subdivided mesh (..., n', C), linearly."""
        return apply_extension(self.extension, values)


def extension_matrix(parent: np.ndarray, num_base: int | None = None) -> sp.csr_matrix:
    """(n',n) sparse matrix E with E @ base = values extended through a `parent` map
    (`Subdivision.parent`: the n base vertices first, each later vertex the midpoint of two
    that precede it).

    Args:
        parent: (n',2) int. num_base: n (default: the rows with parent[i] = (i, i)).
    """
    parent = np.asarray(parent, dtype=np.int64)
    n = int(np.sum(parent[:, 0] == parent[:, 1])) if num_base is None else int(num_base)
    E = sp.identity(n, format="csr")
    start = n
    while start < len(parent):
        # One level at a time: the vertices whose parents all precede `start`.
        stop = start + int(np.argmax(np.r_[parent[start:].max(axis=1) >= start, True]))
        if stop == start:
            raise ValueError(f"parent map: vertex {start} names a parent that does not precede it")
        p = parent[start:stop]
        E = sp.vstack([E, 0.5 * (E[p[:, 0]] + E[p[:, 1]])]).tocsr()
        start = stop
    return E


def apply_extension(extension: sp.csr_matrix, values: np.ndarray) -> np.ndarray:
    """Per-vertex values (..., n, C) -> (..., n', C) through an `extension_matrix` (n',n).

    The result has the values' floating dtype (float32 stays float32; integers give float64).
    """
    v = np.asarray(values)
    n_sub, n = extension.shape
    if v.ndim < 2 or v.shape[-2] != n:
        raise ValueError(f"expected values of shape (..., {n}, C), got {v.shape}")
    dtype = np.result_type(v.dtype, np.float32)
    batch = v.shape[:-2]
    flat = np.moveaxis(v, -2, 0).reshape(n, -1)
    out = np.asarray(extension @ flat.astype(np.float64)).reshape((n_sub,) + batch + v.shape[-1:])
    return np.moveaxis(out, 0, -2).astype(dtype, copy=False)


def apply_parent(values: np.ndarray, parent: np.ndarray) -> np.ndarray:
    """Extend per-vertex values (..., n, C) through a `parent` map (n',2) by midpoints.

    Builds the `extension_matrix` each call; to extend many arrays, keep the matrix
    (`Subdivision.extension`) and use `apply_extension`.
    """
    v = np.asarray(values)
    return apply_extension(extension_matrix(parent, v.shape[-2]), v)


def subdivide(faces: np.ndarray, num_vertices: int, levels: int) -> Subdivision:
    """Split every triangle into four, `levels` times (0, 1 or 2 in practice).

    No geometric perturbation: positions and uv of new vertices are edge midpoints.
    Seam copies stay split (each chart gets its own midpoint).
    """
    f = np.asarray(faces, dtype=np.int64)
    parent = np.stack([np.arange(num_vertices)] * 2, axis=1)
    n = num_vertices
    for _ in range(levels):
        e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        e_sorted = np.sort(e, axis=1)
        uniq, inverse = np.unique(e_sorted, axis=0, return_inverse=True)
        mid = n + inverse.reshape(3, len(f))  # midpoint index of edges (01, 12, 20) per face
        m01, m12, m20 = mid
        a, b, c = f[:, 0], f[:, 1], f[:, 2]
        f = np.concatenate([
            np.stack([a, m01, m20], 1),
            np.stack([m01, b, m12], 1),
            np.stack([m20, m12, c], 1),
            np.stack([m01, m12, m20], 1),
        ])
        parent = np.concatenate([parent, uniq])
        n += len(uniq)
    return Subdivision(faces=f.astype(np.int32), parent=parent.astype(np.int32))


def barycentric_2d(points: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (k,3) float64 of 2-D points (k,2) in triangles (k,3,2)."""
    p = np.asarray(points, dtype=np.float64)
    t = np.asarray(tri, dtype=np.float64)
    v0 = t[:, 1] - t[:, 0]
    v1 = t[:, 2] - t[:, 0]
    v2 = p - t[:, 0]
    det = v0[:, 0] * v1[:, 1] - v0[:, 1] * v1[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        b1 = (v2[:, 0] * v1[:, 1] - v2[:, 1] * v1[:, 0]) / det
        b2 = (v0[:, 0] * v2[:, 1] - v0[:, 1] * v2[:, 0]) / det
    return np.stack([1.0 - b1 - b2, b1, b2], axis=1)


def uv_charts(faces: np.ndarray, n: int) -> np.ndarray:
    """Chart label per vertex (n,) int64: connected components of the face graph.

    UV seams are split vertices, so each UV chart is one component.
    """

    return csgraph.connected_components(adjacency(faces, n), directed=False)[1].astype(np.int64)


def charts_through_parent(base_charts: np.ndarray, faces: np.ndarray, num_vertices: int) -> np.ndarray:
    """Chart labels on a subdivided mesh (its first len(base_charts) vertices are the base
    vertices), numbered like the base mesh's."""
    n = len(base_charts)
    sub = uv_charts(faces, num_vertices)
    lut = np.full(sub.max() + 1, -1, dtype=np.int64)
    lut[sub[:n]] = base_charts
    return lut[sub]


def grid_faces(rows: int, columns: int, charts: int = 1) -> np.ndarray:
    """Triangles of `charts` regular grids stored one after another, each `rows` x
    (`columns` + 1) vertices in row-major order: (charts * 2 * (rows-1) * columns, 3) int32.

    The quad diagonal alternates (checkerboard), so diagonal folds do not alias along one
    direction; both triangles of a quad keep the orientation of (row, column) order.
    """
    i, j = np.meshgrid(np.arange(rows - 1), np.arange(columns), indexing="ij")
    even = ((i + j) % 2 == 0).ravel()[:, None]
    faces = []
    for chart in range(charts):
        v00 = (chart * rows * (columns + 1) + i * (columns + 1) + j).ravel()
        v01, v10 = v00 + 1, v00 + columns + 1
        v11 = v10 + 1
        t1 = np.where(even, np.stack([v00, v01, v11], 1), np.stack([v00, v01, v10], 1))
        t2 = np.where(even, np.stack([v00, v11, v10], 1), np.stack([v01, v11, v10], 1))
        faces.append(np.stack([t1, t2], axis=1).reshape(-1, 3))
    return np.concatenate(faces).astype(np.int32)
