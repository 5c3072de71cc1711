"""Which Laplacian should the harmonic fill use? Both library operators, side by side on the
built-in garment: the cotangent Laplacian (`potpourri3d.cotan_laplacian`) and the intrinsic
Delaunay Laplacian (`robust_laplacian`), as `mvtex.sliding.fill.laplacian_matrix` builds them.

    python benchmarks/fill_laplacian.py DATASET [RIG] [POSES_SPEC]

Defaults: rig stereo, the test poses. Two measures per operator, on the same slide jobs:

- eval: SqrtMSE of the texcoords against gt over all pixels and same-chart pixels, and
  the ratio baseline / texcoords (what `mvtex eval` reports);
- held-out fill: in every job, the assigned vertices within 3 cm (on the reference shape)
  of 10 random assigned vertices are unassigned, filled, and compared with the ray's d
  there (RMSE in uv units). It measures the fill alone where the truth is known.
"""

import json
import sys
from dataclasses import replace

import numpy as np

from mvtex.data.dataset import load_dataset, reference_shape
from mvtex.data.rig import as_rig
from mvtex.evaluation.uv import masked_uv_error, texcoord_image
from mvtex.render.context import GLContext
from mvtex.sliding.fill import LAPLACIANS, FillSystem, fill
from mvtex.sliding.options import SlideOptions
from mvtex.sliding.pose import slide_pose
from mvtex.sliding.topology import build_topology


def main(dataset_path: str, rig_spec: str = "stereo", spec: str = "test", seed: int = 0) -> dict:
    ds = load_dataset(dataset_path)
    rig = as_rig(rig_spec)
    poses = ds.select(spec)
    options = SlideOptions(subdiv=1)
    base = build_topology(ds.faces, ds.uv, reference_shape(ds), options.subdiv)
    ref = base.reference_sub
    topologies = {kind: replace(base, fill_system=FillSystem(base.faces, ref, base.groups, laplacian=kind))
                  for kind in LAPLACIANS}
    stats = {kind: {"base": [], "tc": [], "base_same": [], "tc_same": [], "held_out_sq": [], "held_out_n": 0}
             for kind in LAPLACIANS}
    rng = np.random.default_rng(seed)
    with GLContext() as ctx:
        for k in poses:
            gt, inferred = np.asarray(ds.gt[k], np.float64), np.asarray(ds.inferred[k], np.float64)
            X = base.positions(inferred)
            for cam in rig:
                uv_g, r_g = texcoord_image(ctx, gt, ds.faces, ds.uv, cam)
                uv_b, r_b = texcoord_image(ctx, inferred, ds.faces, ds.uv, cam)
                chart_g = np.where(r_g.mask, base.gt_chart[np.maximum(r_g.tri_id, 0)], -1)
                chart_b = np.where(r_b.mask, base.gt_chart[np.maximum(r_b.tri_id, 0)], -1)
                first = None
                for kind, topo in topologies.items():
                    d, assigned = slide_pose(gt, inferred, ds.faces, ds.uv, cam, topo.subdivision, options,
                                             topology=topo, ctx=ctx)
                    if first is None:
                        first = assigned
                        centres = rng.choice(np.flatnonzero(assigned), size=min(10, int(assigned.sum())),
                                             replace=False)
                        near = np.zeros(len(ref), bool)
                        for c in centres:
                            near |= np.linalg.norm(ref - ref[c], axis=1) < 0.03
                        held = near & assigned
                    assert np.array_equal(assigned, first)  # the fill never changes what is assigned
                    uv_t, r_t = texcoord_image(ctx, X, topo.faces, topo.uv + d, cam)
                    chart_t = np.where(r_t.mask, base.chart[topo.faces[np.maximum(r_t.tri_id, 0), 0]], -1)
                    s = stats[kind]
                    s["base"].append(masked_uv_error(uv_b, r_b.mask, uv_g, r_g.mask)[1])
                    s["tc"].append(masked_uv_error(uv_t, r_t.mask, uv_g, r_g.mask)[1])
                    s["base_same"].append(masked_uv_error(uv_b, chart_b == chart_g, uv_g, chart_g >= 0)[1])
                    s["tc_same"].append(masked_uv_error(uv_t, chart_t == chart_g, uv_g, chart_g >= 0)[1])
                    refilled = fill(topo.faces, X, d, assigned & ~held, "harmonic", topo.groups,
                                    system=topo.fill_system)
                    s["held_out_sq"].append(float(np.sum((refilled[held] - d[held]).astype(np.float64) ** 2)))
                    s["held_out_n"] += int(held.sum())
    result = {}
    for kind, s in stats.items():
        result[kind] = {
            "images": len(s["tc"]),
            "sqrt_mse_texcoords": float(np.nanmean(s["tc"])),
            "ratio": float(np.nanmean(s["base"]) / np.nanmean(s["tc"])),
            "sqrt_mse_same_chart_texcoords": float(np.nanmean(s["tc_same"])),
            "ratio_same_chart": float(np.nanmean(s["base_same"]) / np.nanmean(s["tc_same"])),
            "held_out_vertices": s["held_out_n"],
            "held_out_rmse_uv": float(np.sqrt(np.sum(s["held_out_sq"]) / max(s["held_out_n"], 1))),
        }
    print(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main(*sys.argv[1:])
