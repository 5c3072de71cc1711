"""What texture sliding needs of the mesh that does not change with the pose
(`SlideTopology`, built once per dataset and subdivision level).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mvtex.data.mesh import Subdivision, edges, extension_matrix, face_neighbours, subdivide, uv_charts, weld_groups
from mvtex.sliding.fill import FillSystem


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
        reference: (n,3) the reference shape (`mvtex.data.dataset.reference_shape`): finds seam
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


@dataclass(frozen=True)
class BodyTopology:
    """The body (an opaque occluder that is not cloth) as the hit search sees it, built once
    per dataset.

    Attributes:
        faces: (mb,3) int64 body faces (indices into the body's own vertices), C-contiguous.
        num_cloth_faces: m, the cloth's base faces (the rasters number body face j as m + j).
    """

    faces: np.ndarray
    num_cloth_faces: int


def body_topology(body_faces: np.ndarray, topology: SlideTopology) -> BodyTopology:
    """The hit search's view of a body with `body_faces` (mb,3) beside the cloth of `topology`."""
    body_faces = np.ascontiguousarray(body_faces, dtype=np.int64)
    return BodyTopology(faces=body_faces, num_cloth_faces=len(topology.face_neighbours))
