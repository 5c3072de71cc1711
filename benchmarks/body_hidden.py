"""Material the body hides, assigned by texture sliding: `slide` against a ray cast.

    python benchmarks/body_hidden.py DATA [DATA ...] [--rigs stereo square4 trapezoid12]
        [--openings] [--poses 0:40] [--subdiv 1] [--json out.json]

For every (pose, camera) job it slides the worn dataset (`slide_pose` with the body, as
`mvtex slide` does) and casts every subdivided inferred vertex's ray from the camera with
Embree (`trimesh.ray.ray_pyembree`, needs `embreex`) against the body alone and against the
ground-truth cloth alone. Embree works in float32: the triangles it reports for the ray and
for four rays tilted 1e-5 rad around it, with the faces sharing a vertex with them, are
intersected with the ray again in float64 (Möller–Trumbore), and the nearest hit counts.
A vertex (projected into the image) is hidden by the body when the body meets its ray
before the vertex (t < 1, t = 1 at the vertex) or before the first gt cloth hit (exact
ties go to the cloth), DESIGN §5 "The body". Prints a Markdown table per dataset and rig:
hidden vertices, those of them `slide` assigns, and their share. `--openings` adds four
cameras looking into the garment's top and bottom openings (a collar, a waist, a hem).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np


def _intersector(positions: np.ndarray, faces: np.ndarray):
    import trimesh
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    return RayMeshIntersector(trimesh.Trimesh(vertices=positions, faces=faces, process=False))


def first_hit_t(intersector, positions: np.ndarray, faces: np.ndarray, ring: np.ndarray, origin: np.ndarray,
                dirs: np.ndarray) -> np.ndarray:
    """(k,) float64 t of each ray's first hit on the mesh (t in units of dirs[k]; inf for
    none). Embree (float32) casts each ray and four rays tilted 1e-5 rad around it (a ray
    through a vertex or along an edge can slip between the faces there); the faces they
    hit and their `ring` neighbours (k,r) (-1 none) are intersected with the ray itself in
    float64 (Möller–Trumbore), and the nearest hit counts."""
    from mvtex.sliding.hits import intersect_pairs

    unit = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    side = np.cross(unit, np.where(np.abs(unit[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]]))
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    other = np.cross(unit, side)
    t = np.full(len(dirs), np.inf)
    for tilt in (0 * side, 1e-5 * side, -1e-5 * side, 1e-5 * other, -1e-5 * other):
        tilted = unit + tilt
        tri, ray = intersector.intersects_id(np.broadcast_to(origin, unit.shape), tilted, multiple_hits=False,
                                             return_locations=False)
        if len(ray) == 0:
            continue
        cand = np.concatenate([tri[:, None], ring[tri]], axis=1)
        rays = np.repeat(ray, cand.shape[1])
        cand = cand.ravel()
        keep = cand >= 0
        rays, cand = rays[keep], cand[keep]
        np.minimum.at(t, rays, intersect_pairs(origin, dirs[rays], positions, faces, cand)[0])
    return t


def vertex_ring(faces: np.ndarray) -> np.ndarray:
    """(m, r) faces sharing a vertex with each face (-1 padded)."""
    import scipy.sparse as sp

    m = len(faces)
    n = int(faces.max()) + 1
    inc = sp.csr_matrix((np.ones(3 * m), (np.repeat(np.arange(m), 3), faces.ravel())), shape=(m, n))
    adj = (inc @ inc.T).tocsr()
    counts = np.diff(adj.indptr)
    out = np.full((m, counts.max()), -1, np.int64)
    col = np.arange(adj.nnz) - np.repeat(adj.indptr[:-1], counts)
    out[np.repeat(np.arange(m), counts), col] = adj.indices
    return out


def body_hidden(camera, X: np.ndarray, gt: np.ndarray, faces: np.ndarray, gt_ring: np.ndarray,
                body_positions: np.ndarray, body_faces: np.ndarray, body_ring: np.ndarray) -> dict:
    """Per vertex of X: in the image, and hidden by the body (before the vertex, or before
    the first gt cloth hit)."""
    origin = camera.center
    pixels, z = camera.project(X)
    in_image = camera.in_image(pixels, z)
    dirs = X - origin
    t_body = first_hit_t(_intersector(body_positions, body_faces), body_positions, body_faces, body_ring, origin,
                         dirs)
    t_cloth = first_hit_t(_intersector(gt, faces), gt, faces, gt_ring, origin, dirs)
    before_vertex = in_image & (t_body < 1)
    before_cloth = in_image & (t_body < t_cloth)
    return {"hidden": before_vertex | before_cloth, "before_vertex": before_vertex, "before_cloth": before_cloth}


def openings_rig(gt: np.ndarray) -> list:
    """Four cameras 0.6 m above and below the garment (y up), looking into its top opening
    (a collar, a waist) from the front and the back and into its bottom opening (a hem)
    from the front and the side."""
    from mvtex.data.camera import look_at

    top, bottom = gt[:, 1].max(), gt[:, 1].min()
    x, z = gt[:, 0].mean(), gt[:, 2].mean()
    views = {"top_front": ((x, top + 0.6, z + 0.5), (x, top - 0.05, z)),
             "top_back": ((x, top + 0.6, z - 0.5), (x, top - 0.05, z)),
             "bottom_front": ((x, bottom - 0.6, z + 0.5), (x, bottom + 0.05, z)),
             "bottom_side": ((x + 0.5, bottom - 0.6, z + 0.2), (x, bottom + 0.05, z))}
    return [look_at(name, centre, target, width=512, height=512, focal=600.0)
            for name, (centre, target) in views.items()]


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", nargs="+", type=Path, help="worn dataset directories (with a body)")
    parser.add_argument("--rigs", nargs="*", default=["stereo", "square4", "trapezoid12"])
    parser.add_argument("--poses", default="0:40", help="pose SPEC (default 0:40)")
    parser.add_argument("--subdiv", type=int, default=1)
    parser.add_argument("--openings", action="store_true",
                        help="also a rig of four cameras looking into the garment's top and bottom openings")
    parser.add_argument("--json", type=Path, help="also write the rows here")
    args = parser.parse_args(argv)

    from mvtex.data.dataset import load_dataset, parse_pose_spec, reference_shape
    from mvtex.data.rig import load_rig, resolve_rig
    from mvtex.render.context import GLContext
    from mvtex.sliding.options import SlideOptions
    from mvtex.sliding.pose import slide_pose
    from mvtex.sliding.topology import body_topology, build_topology

    options = SlideOptions(subdiv=args.subdiv)
    rows = []
    with GLContext() as ctx:
        for data in args.data:
            ds = load_dataset(data)
            if ds.body is None:
                raise SystemExit(f"{data}: the dataset has no body")
            poses = parse_pose_spec(args.poses, ds.num_poses)
            topo = build_topology(ds.faces, ds.uv, reference_shape(ds), options.subdiv)
            body_topo = body_topology(ds.body.faces, topo)
            faces = np.asarray(ds.faces, np.int64)
            body_faces = np.asarray(ds.body.faces, np.int64)
            gt_ring, body_ring = vertex_ring(faces), vertex_ring(body_faces)
            rigs = {name: load_rig(resolve_rig(name)) for name in args.rigs}
            if args.openings:
                rigs["openings"] = openings_rig(np.asarray(ds.gt[poses[0]], np.float64))
            for rig_name, rig in rigs.items():
                counts = {"hidden": 0, "assigned": 0, "before_vertex": 0, "assigned_before_vertex": 0,
                          "before_cloth": 0, "assigned_before_cloth": 0, "assigned_total": 0}
                seconds = 0.0
                for k in poses:
                    gt = np.asarray(ds.gt[k], np.float64)
                    inferred = np.asarray(ds.inferred[k], np.float64)
                    body_positions = np.asarray(ds.body.pose(k), np.float64)
                    X = topo.positions(inferred)
                    for cam in rig:
                        start = time.perf_counter()
                        _, assigned = slide_pose(gt, inferred, faces, ds.uv, cam, topo.subdivision, options,
                                                 topology=topo, ctx=ctx, body=(body_positions, body_faces),
                                                 body_topo=body_topo)
                        seconds += time.perf_counter() - start
                        ref = body_hidden(cam, X, gt, faces, gt_ring, body_positions, body_faces, body_ring)
                        counts["assigned_total"] += int(assigned.sum())
                        for key in ("hidden", "before_vertex", "before_cloth"):
                            counts[key] += int(ref[key].sum())
                            counts["assigned" if key == "hidden" else f"assigned_{key}"] += int(
                                (ref[key] & assigned).sum())
                    print(f"{ds.name} {rig_name} pose {k}: {counts['assigned']} of {counts['hidden']}",
                          file=sys.stderr, end="\r")
                print(file=sys.stderr)
                rows.append({"dataset": str(data), "garment": ds.name, "rig": rig_name, "poses": len(poses),
                             "jobs": len(poses) * len(rig), "slide_seconds": seconds, **counts,
                             "share": counts["assigned"] / max(counts["hidden"], 1)})
                print(f"{ds.name} {rig_name}: {counts['assigned']} of {counts['hidden']} assigned", file=sys.stderr)
    print("| dataset | rig | jobs | hidden by the body | of them assigned | share | (before the vertex) "
          "| (before the gt cloth) |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['garment']} | {r['rig']} | {r['jobs']} | {r['hidden']:,} | {r['assigned']:,} | "
              f"{100 * r['share']:.3f} % | {r['assigned_before_vertex']} of {r['before_vertex']:,} | "
              f"{r['assigned_before_cloth']} of {r['before_cloth']:,} |")
    total_hidden = sum(r["hidden"] for r in rows)
    total_assigned = sum(r["assigned"] for r in rows)
    print(f"\nall: {total_assigned:,} of {total_hidden:,} ({100 * total_assigned / max(total_hidden, 1):.3f} %)")
    summary = {"rows": rows, "subdiv": options.subdiv, "poses": args.poses}
    if args.json:
        args.json.write_text(json.dumps(summary, indent=1))
    return summary


if __name__ == "__main__":
    main()
