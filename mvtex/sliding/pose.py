"""Texture sliding of one (pose, camera): T_N and d from the hits, the rejection rules and
the fill (DESIGN §5 steps 4-6), and `slide_pose`, the whole job.
"""

from __future__ import annotations

import numpy as np

from mvtex.data.camera import Camera
from mvtex.data.mesh import Subdivision
from mvtex.render.context import GLContext
from mvtex.render.raster import check_mesh
from mvtex.sliding.fill import fill
from mvtex.sliding.hits import Hits, find_hits_raster
from mvtex.sliding.options import SlideOptions
from mvtex.sliding.topology import BodyTopology, SlideTopology, body_topology, build_topology
from mvtex.util.checks import as_array, check_instance, check_shape
from mvtex.util.errors import OptionError


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
               topology: SlideTopology | None = None, ctx: GLContext | None = None,
               body: tuple[np.ndarray, np.ndarray] | None = None,
               body_topo: BodyTopology | None = None) -> tuple[np.ndarray, np.ndarray]:
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
        body: (positions (nb,3), faces (mb,3)) of the wearer's body in this pose (DESIGN §5
            "The body"): vertices it hides are not visible, rays that meet it before the gt
            cloth are unassigned. None: no body.
        body_topo: `body_topology(faces, topology)` for this body (computed here if None;
            pass it when sliding many poses).

    Returns:
        d: (n',2) float32 displacement T_N - T_G on the subdivided mesh, filled everywhere.
        assigned: (n',) bool, True where d came from the ray.
    """

    gt, faces = check_mesh(gt_positions, faces, "gt_positions")
    inferred, _ = check_mesh(inferred_positions, faces, "inferred_positions")
    check_shape(inferred, "inferred_positions", gt.shape)
    uv = as_array(uv, "uv")
    check_shape(uv, "uv", (len(gt), 2))
    check_instance(camera, Camera, "camera")
    check_instance(subdivision, Subdivision, "subdivision")
    check_instance(options, SlideOptions, "options")
    if topology is not None:
        check_instance(topology, SlideTopology, "topology")
    if body is not None and (not isinstance(body, (tuple, list)) or len(body) != 2):
        raise OptionError("body", "must be (positions (nb,3), faces (mb,3))")
    if body is not None:
        body = check_mesh(body[0], body[1], "body positions")
    faces = faces.astype(np.int64)
    if topology is None:
        levels = int(round(np.log(len(subdivision.faces) / max(len(faces), 1)) / np.log(4)))
        topology = build_topology(faces, uv, gt, levels)
    X = topology.positions(inferred)
    occluder = None
    if body is not None:
        occluder = (np.asarray(body[0], np.float64), body_topo or body_topology(body[1], topology))
    if ctx is None:

        with GLContext() as own:
            hits = find_hits_raster(own, gt, inferred, faces, X, topology, camera, options, body=occluder)
    else:
        hits = find_hits_raster(ctx, gt, inferred, faces, X, topology, camera, options, body=occluder)
    return displacement_from_hits(hits, faces, uv, X, topology, options)
