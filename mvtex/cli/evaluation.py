"""`mvtex eval`: the material error and the per-pixel uv error of a texcoord set against its baseline."""

from __future__ import annotations

import contextlib
from pathlib import Path

from mvtex.cli.common import add_common, add_rig, add_workers, emit, output, rig_of


def register(sub) -> None:
    p = sub.add_parser("eval", help="material error (mm) and per-pixel uv error: baseline vs a texcoord set")
    p.add_argument("dataset", type=Path, help="dataset directory")
    add_rig(p, "the cameras (those of the texcoord set are evaluated)", from_texcoords=True)
    p.add_argument("--texcoords", metavar="TC", type=Path, required=True, help="texcoord set to evaluate")
    p.add_argument("--poses", metavar="SPEC", help="pose SPEC (default: the texcoord set's poses)")
    p.add_argument("--heatmaps", metavar="DIR", type=Path, help="write error heatmaps (PNG per image) into this folder")
    add_workers(p, "1")
    add_common(p)
    p.set_defaults(run=cmd_eval)


def summary_text(result) -> str:
    """An `Evaluation`'s headline numbers, the material error first (docs/evaluation.md names
    each measure)."""
    s, c, m, a = result.sqrt_mse, result.sqrt_mse_same_chart, result.material_rmse_m, result.material_rmse_assigned_m
    lines = []
    if m is not None:
        lines.append(f"material error: inferred {m.inferred.mean*1e3:.2f} ± {m.inferred.std*1e3:.2f} mm -> "
                     f"texcoords {m.texcoords.mean*1e3:.2f} ± {m.texcoords.std*1e3:.2f} mm, "
                     f"ratio {result.ratio_material:.2f} ({result.num_images} images, all pixels)")
        lines.append(f"material error, assigned triangles ({100 * result.assigned_share.mean:.1f} % of pixels): "
                     f"{a.inferred.mean*1e3:.2f} -> {a.texcoords.mean*1e3:.2f} mm, "
                     f"ratio {result.ratio_material_assigned:.2f}")
    lines.append(f"uv error (the paper's SqrtMSE, e-3): {s.inferred.mean*1e3:.2f} ± {s.inferred.std*1e3:.2f} -> "
                 f"{s.texcoords.mean*1e3:.2f} ± {s.texcoords.std*1e3:.2f}, ratio {result.ratio:.2f}"
                 + ("" if m is not None else f" ({result.num_images} images)"))
    lines.append(f"uv error, same chart (e-3): {c.inferred.mean*1e3:.3f} -> {c.texcoords.mean*1e3:.3f}, "
                 f"ratio {result.ratio_same_chart:.2f}")
    o = result.original_inferred
    if o is not None:  # a corrected set: "inferred" above is the corrected mesh
        material = "" if o["material_rmse_m"] is None else (
            f"material error {o['material_rmse_m'].mean*1e3:.2f} mm (ratio {result.ratio_material_original:.2f}), ")
        lines.append(f"corrected set, the mesh before the correction: {material}uv error (e-3) "
                     f"{o['sqrt_mse'].mean*1e3:.2f} (ratio {result.ratio_original:.2f})")
    return "\n".join(lines)


def cmd_eval(args):
    from mvtex.data.dataset import load_dataset
    from mvtex.data.texcoords import open_texcoords
    from mvtex.evaluation.evaluate import evaluate

    dataset = load_dataset(args.dataset)
    dataset.require_gt("eval")
    tc = open_texcoords(args.texcoords, dataset.num_vertices, num_poses=dataset.num_poses)
    rig = rig_of(args, names=tc.cameras)
    poses = dataset.select(args.poses) if args.poses else None
    with output(args, "eval", args.heatmaps) if args.heatmaps else contextlib.nullcontext():
        result = evaluate(dataset, rig, tc, poses=poses, cameras=rig.names, heatmaps=args.heatmaps,
                          progress=not args.quiet, workers=args.workers or 1, scheduler=args.scheduler)
    emit(args, result, summary_text(result))
