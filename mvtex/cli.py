"""`mvtex` command line: parses arguments and calls the library functions that Python users
call too. No logic lives here. Exit codes: 0 success, 2 bad usage or bad input (one line on
stderr naming the file and the problem), 1 unexpected failure.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Sequence

from . import __version__
from .errors import InputError


def _add_json(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")


def _add_progress(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mvtex", description="Texture sliding for learned cloth: per-camera "
                                     "texture-coordinate perturbations, evaluation, multi-view reconstruction.")
    parser.add_argument("--version", action="version", version=f"mvtex {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    p = sub.add_parser("synth", help="write the built-in garment dataset")
    p.add_argument("out", type=Path)
    p.add_argument("--poses", type=int, default=300, help="number of poses (default 300)")
    p.add_argument("--seed", type=int, default=0)
    _add_json(p)

    p = sub.add_parser("import", help="OBJ/PLY sequences (same connectivity) -> dataset")
    p.add_argument("out", type=Path)
    p.add_argument("--gt", required=True, help="glob of ground-truth meshes (sorted order = pose order)")
    p.add_argument("--inferred", required=True, help="glob of inferred meshes, paired in sorted order")
    p.add_argument("--poses", type=Path, help="pose vectors: .npy (K,P) or text rows")
    p.add_argument("--name", help="dataset name (default: the folder name)")
    _add_progress(p)

    p = sub.add_parser("render", help="textured PNGs of gt and inferred per camera")
    p.add_argument("dataset", type=Path)
    p.add_argument("--rig", required=True, help="rig YAML, or a built-in rig name (stereo, square4, trapezoid12)")
    p.add_argument("--pose", type=int, required=True)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--texcoords", type=Path, help="texcoord set: draw the inferred mesh with its texcoords")
    p.add_argument("--raster", action="store_true", help="also write raster dumps (tri_id, bary, depth, uv)")
    p.add_argument("--cameras", help="comma-separated camera names (default: all)")
    _add_progress(p)

    p = sub.add_parser("slide", help="texture sliding over a dataset and a rig -> texcoord set")
    p.add_argument("dataset", type=Path)
    p.add_argument("--rig", required=True)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--poses", default="all", help="all, train, val, test, a:b or 3,5,7 (default all)")
    p.add_argument("--subdiv", type=int, default=1, choices=(0, 1, 2))
    p.add_argument("--fill", default="harmonic", choices=("harmonic", "fmm"))
    p.add_argument("--max-displacement", type=float, help="unassign vertices with |d| above this (uv units)")
    p.add_argument("--cameras", help="comma-separated camera names (default: all)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--workers", type=int, default=None,
                   help="local worker processes (default: one per core for long runs, else 1)")
    g.add_argument("--scheduler", help="Dask scheduler address (tcp://host:8786)")
    _add_progress(p)

    p = sub.add_parser("eval", help="per-pixel texture-coordinate error: baseline vs a texcoord set")
    p.add_argument("dataset", type=Path)
    p.add_argument("--rig", required=True)
    p.add_argument("--texcoords", type=Path, required=True)
    p.add_argument("--poses", help="pose SPEC (default: the texcoord set's poses)")
    p.add_argument("--heatmaps", type=Path, help="write error heatmaps here")
    _add_json(p)
    _add_progress(p)

    p = sub.add_parser("triangulate", help="multi-view reconstruction of one pose -> PLY + COLMAP model")
    p.add_argument("dataset", type=Path)
    p.add_argument("--rig", required=True)
    p.add_argument("--texcoords", type=Path, required=True)
    p.add_argument("--pose", type=int, required=True)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--smooth", action="store_true", help="smooth the reconstructed displacement (noisy inputs)")
    p.add_argument("--max-reprojection-px", type=float, default=2.0, help="reject points above this (default 2 px)")
    p.add_argument("--max-surface-distance", type=float, default=0.05,
                   help="reject points farther than this from the inferred surface (default 0.05 m)")
    _add_json(p)
    _add_progress(p)

    p = sub.add_parser("train", help="train a texture sliding network (one camera, or all conditioned on the camera)")
    p.add_argument("dataset", type=Path, help="dataset directory")
    p.add_argument("--texcoords", type=Path, required=True, help="texcoord set with the training targets")
    p.add_argument("--camera", help="train this camera's network (default: one network for every camera of "
                   "--texcoords, conditioned on the camera)")
    p.add_argument("--rig", help="rig of the texcoord set's cameras (needed without --camera: builtin name or "
                   "rig.yaml; default TEXCOORDS/rig.yaml)")
    p.add_argument("--out", type=Path, required=True, help="model directory to write")
    p.add_argument("--arch", choices=("unet", "paper"), default="unet",
                   help="unet: geometry images of the inferred mesh + pose, any camera (default; best up to "
                   "~500 poses); paper: pose only, per camera (best with ~1,000 poses per camera)")
    p.add_argument("--epochs", type=int, help="most training epochs (default 60)")
    p.add_argument("--resolution", type=int, help="atlas image size (default 64 on CPU)")
    p.add_argument("--device", default=None, help="cpu, cuda, cuda:0 ... (default: cuda if available)")
    p.add_argument("--seed", type=int, default=0, help="seed of initialisation and batch order (default 0)")
    _add_json(p)
    _add_progress(p)

    p = sub.add_parser("predict", help="trained networks -> texcoord set")
    p.add_argument("dataset", type=Path, help="dataset directory")
    p.add_argument("--model", type=Path, action="append", required=True,
                   help="a trained model (repeat: one per camera, or a camera-conditioned one)")
    p.add_argument("--out", type=Path, required=True, help="texcoord set directory to write")
    p.add_argument("--poses", default="all", help="all, train, val, test, a:b or 3,5,7 (default all)")
    p.add_argument("--rig", help="predict these cameras (a camera-conditioned model serves any camera; "
                   "default: the models' own cameras)")
    _add_progress(p)

    p = sub.add_parser("bench", help="throughput: raster vs ray-cast sliding, and eval")
    p.add_argument("dataset", type=Path)
    p.add_argument("--rig", required=True)
    p.add_argument("--poses", default="0:20", help="poses to time (default 0:20)")
    p.add_argument("--subdiv", type=int, default=1, choices=(0, 1, 2))
    p.add_argument("--workers", type=int, default=2, help="worker processes for the parallel measurement (default 2)")
    _add_json(p)
    _add_progress(p)

    p = sub.add_parser("demo", help="the whole pipeline on the built-in garment")
    p.add_argument("--out", type=Path, default=Path("mvtex-demo"))
    p.add_argument("--poses", type=int, default=120, help="poses to synthesize (default 120)")
    p.add_argument("--epochs", type=int, help="TSNN epochs (default: the training default)")
    _add_json(p)
    _add_progress(p)
    return parser


def _cameras(value: str | None) -> list[str] | None:
    return [c.strip() for c in value.split(",") if c.strip()] if value else None


def _load_rig(spec: str):
    from .camera import load_rig, resolve_rig

    path = resolve_rig(spec)
    return load_rig(path), str(path)


def _emit(args, result: dict, text: str) -> None:
    if getattr(args, "json", False):
        print(json.dumps(result))
    else:
        print(text)


def cmd_synth(args) -> dict:
    from .synth import SynthOptions, write_synth

    if args.poses < 10:
        raise InputError(None, f"--poses must be at least 10 (got {args.poses})")
    stats = write_synth(args.out, SynthOptions(num_poses=args.poses, seed=args.seed))
    _emit(args, stats, f"wrote {args.out}: " + ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                                                           for k, v in stats.items()))
    return stats


def cmd_import(args) -> None:
    from .dataset import import_sequences

    path = import_sequences(args.out, args.gt, args.inferred, args.poses, name=args.name, progress=not args.quiet)
    print(f"wrote {path}")


def cmd_render(args) -> None:
    from .dataset import load_dataset
    from .render import render_pose
    from .texcoords import open_texcoords

    dataset = load_dataset(args.dataset)
    rig, rig_path = _load_rig(args.rig)
    rig = rig.select(_cameras(args.cameras), rig_path)
    tc = open_texcoords(args.texcoords, dataset.num_vertices) if args.texcoords else None
    summary = render_pose(dataset, rig, args.pose, args.out, texcoords=tc, raster=args.raster, rig_path=rig_path,
                          progress=not args.quiet)
    print(f"wrote {len(summary['files'])} files to {args.out}")


def cmd_slide(args) -> None:
    from .dataset import load_dataset
    from .sliding import SlideOptions, slide_dataset

    dataset = load_dataset(args.dataset)
    rig, rig_path = _load_rig(args.rig)
    rig = rig.select(_cameras(args.cameras), rig_path)
    options = SlideOptions(subdiv=args.subdiv, fill=args.fill, max_displacement=args.max_displacement)
    if args.workers is not None and args.workers < 1:
        raise InputError(None, f"--workers must be at least 1 (got {args.workers})")
    out = slide_dataset(dataset, rig, args.out, poses=dataset.select(args.poses), options=options,
                        workers=args.workers, scheduler=args.scheduler, progress=not args.quiet)
    print(f"wrote {out}")


def cmd_eval(args) -> dict:
    from .dataset import load_dataset
    from .metrics import evaluate
    from .texcoords import open_texcoords

    dataset = load_dataset(args.dataset)
    rig, rig_path = _load_rig(args.rig)
    tc = open_texcoords(args.texcoords, dataset.num_vertices)
    poses = dataset.select(args.poses) if args.poses else None
    result = evaluate(dataset, rig.select(tc.cameras, rig_path), tc, poses=poses, heatmaps=args.heatmaps,
                      progress=not args.quiet)
    s, c = result["sqrt_mse"], result["sqrt_mse_same_chart"]
    _emit(args, result, f"{result['num_images']} images: SqrtMSE inferred {s['inferred']['mean']*1e3:.3f} ± "
          f"{s['inferred']['std']*1e3:.3f} e-3, texcoords {s['texcoords']['mean']*1e3:.3f} ± "
          f"{s['texcoords']['std']*1e3:.3f} e-3, ratio {result['ratio']:.2f}; same-chart pixels: "
          f"{c['inferred']['mean']*1e3:.3f} -> {c['texcoords']['mean']*1e3:.3f} e-3, ratio {result['ratio_same_chart']:.2f}")
    return result


def cmd_triangulate(args) -> dict:
    from .dataset import load_dataset
    from .recon import ReconOptions, triangulate_pose
    from .texcoords import open_texcoords

    dataset = load_dataset(args.dataset)
    rig, rig_path = _load_rig(args.rig)
    tc = open_texcoords(args.texcoords, dataset.num_vertices)
    result = triangulate_pose(dataset, rig.select(tc.cameras, rig_path), tc, args.pose, args.out,
                              ReconOptions(smooth=args.smooth, max_reprojection_px=args.max_reprojection_px,
                                           max_surface_distance_m=args.max_surface_distance),
                              progress=not args.quiet)
    _emit(args, result, f"pose {result['pose']}: {result['num_triangulated']}/{result['num_vertices']} vertices "
          f"triangulated; RMSE inferred {result['rmse_m']['inferred']*1e3:.2f} mm -> reconstructed "
          f"{result['rmse_m']['reconstructed']*1e3:.2f} mm; wrote {args.out}")
    return result


def cmd_train(args) -> dict:
    from dataclasses import replace

    from .dataset import load_dataset
    from .texcoords import open_texcoords
    from .tsnn.train import TrainOptions, train

    dataset = load_dataset(args.dataset)
    tc = open_texcoords(args.texcoords, dataset.num_vertices)
    options = TrainOptions(seed=args.seed, arch=args.arch)
    changes = {k: getattr(args, k) for k in ("epochs", "resolution", "device") if getattr(args, k) is not None}
    options = replace(options, **changes)
    rig = None
    if args.camera is None:
        if args.rig is None and not (args.texcoords / "rig.yaml").is_file():
            raise InputError(args.texcoords, "one network for every camera needs their rig: give --rig "
                             "(or --camera NAME for one camera's network)")
        rig, _ = _load_rig(args.rig or str(args.texcoords / "rig.yaml"))
    try:
        result = train(dataset, tc, args.out, camera=args.camera, rig=rig, options=options, progress=not args.quiet)
    except ValueError as err:
        raise InputError(None, str(err)) from None
    _emit(args, result, f"wrote {args.out} ({result['arch']}, {', '.join(result['cameras'])})")
    return result


def cmd_predict(args) -> None:
    from .dataset import load_dataset
    from .tsnn.predict import predict

    dataset = load_dataset(args.dataset)
    rig = _load_rig(args.rig)[0] if args.rig else None
    out = predict(dataset, args.model, args.out, poses=dataset.select(args.poses), rig=rig, progress=not args.quiet)
    print(f"wrote {out}")


def cmd_bench(args) -> dict:
    from .bench import run_bench
    from .dataset import load_dataset

    dataset = load_dataset(args.dataset)
    rig, _ = _load_rig(args.rig)
    result = run_bench(dataset, rig, poses=dataset.select(args.poses), subdiv=args.subdiv, workers=args.workers,
                       progress=not args.quiet)
    _emit(args, result, json.dumps(result, indent=2))
    return result


def cmd_demo(args) -> dict:
    from .demo import DemoOptions, run_demo

    options = DemoOptions(num_poses=args.poses, epochs=args.epochs)
    result = run_demo(args.out, options, progress=not args.quiet)
    _emit(args, result, result.get("summary_text", json.dumps(result, indent=2)))
    return result


COMMANDS = {"synth": cmd_synth, "import": cmd_import, "render": cmd_render, "slide": cmd_slide, "eval": cmd_eval,
            "triangulate": cmd_triangulate, "train": cmd_train, "predict": cmd_predict, "bench": cmd_bench,
            "demo": cmd_demo}


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exit_:  # argparse: 2 on bad usage, 0 on --help
        return int(exit_.code or 0)
    try:
        COMMANDS[args.command](args)
    except InputError as err:
        print(f"mvtex {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"mvtex {args.command}: interrupted (rerun the same command to resume where supported)", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
