"""`mvtex eval`: the material error and the per-pixel uv error of a texcoord set against its baseline."""

from __future__ import annotations

import contextlib
from pathlib import Path

from mvtex.cli.common import add_common, add_rig, add_workers, emit, load_rig, output


def register(sub) -> None:
    p = sub.add_parser("eval", help="material error (mm) and per-pixel uv error: baseline vs a texcoord set")
    p.add_argument("dataset", type=Path, help="dataset directory")
    add_rig(p, "the cameras (those of the texcoord set are evaluated)")
    p.add_argument("--texcoords", type=Path, required=True, help="texcoord set to evaluate")
    p.add_argument("--poses", help="pose SPEC (default: the texcoord set's poses)")
    p.add_argument("--heatmaps", type=Path, help="write error heatmaps (PNG per image) into this folder")
    add_workers(p, "default 1")
    add_common(p)
    p.set_defaults(run=cmd_eval)


def summary_text(result) -> str:
    """One line of an `Evaluation`'s headline numbers."""
    s, c, m = result.sqrt_mse, result.sqrt_mse_same_chart, result.material_rmse_m
    material = (f"material error inferred {m.inferred.mean*1e3:.2f} ± {m.inferred.std*1e3:.2f} mm, "
                f"texcoords {m.texcoords.mean*1e3:.2f} ± {m.texcoords.std*1e3:.2f} mm, "
                f"ratio {result.ratio_material:.2f}; " if m is not None else "")
    return (f"{result.num_images} images: {material}SqrtMSE inferred {s.inferred.mean*1e3:.3f} ± "
            f"{s.inferred.std*1e3:.3f} e-3, texcoords {s.texcoords.mean*1e3:.3f} ± {s.texcoords.std*1e3:.3f} e-3, "
            f"ratio {result.ratio:.2f}; same-chart pixels: {c.inferred.mean*1e3:.3f} -> "
            f"{c.texcoords.mean*1e3:.3f} e-3, ratio {result.ratio_same_chart:.2f}")


def cmd_eval(args):
    from mvtex.data.dataset import load_dataset
    from mvtex.data.texcoords import open_texcoords
    from mvtex.evaluation.evaluate import evaluate

    dataset = load_dataset(args.dataset)
    rig, rig_path = load_rig(args.rig)
    tc = open_texcoords(args.texcoords, dataset.num_vertices, num_poses=dataset.num_poses)
    poses = dataset.select(args.poses) if args.poses else None
    rig = rig.select(tc.cameras, rig_path)
    with output(args, "eval", args.heatmaps) if args.heatmaps else contextlib.nullcontext():
        result = evaluate(dataset, rig_path, tc, poses=poses, cameras=rig.names, heatmaps=args.heatmaps,
                          progress=not args.quiet, workers=args.workers or 1, scheduler=args.scheduler)
    emit(args, result, summary_text(result))
