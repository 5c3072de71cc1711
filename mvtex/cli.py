"""`mvtex` command line: parses arguments and calls the library functions that Python users
call too. No logic lives here. Exit codes: 0 success, 2 bad usage or bad input (one line on
stderr naming the file and the problem), 1 unexpected failure.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import re
import sys
from pathlib import Path
from typing import Sequence

from . import __version__
from .errors import InputError
from .io import claim_output, dumps_strict


def _add_json(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")


def _add_progress(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def _add_overwrite(p: argparse.ArgumentParser) -> None:
    p.add_argument("--overwrite", action="store_true",
                   help="replace (or, with --heatmaps, write into) an existing output directory that this "
                   "command did not write")


def _add_workers(p: argparse.ArgumentParser, default_help: str) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("--workers", type=int, default=None, help=f"local worker processes ({default_help})")
    g.add_argument("--scheduler", help="Dask scheduler address (tcp://host:8786)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mvtex", description="Texture sliding for learned cloth: per-camera "
                                     "texture-coordinate perturbations, evaluation, multi-view reconstruction.")
    parser.add_argument("--version", action="version", version=f"mvtex {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    p = sub.add_parser("synth", help="write the built-in garment dataset")
    p.add_argument("out", type=Path, help="dataset directory to write")
    p.add_argument("--poses", type=int, default=300, help="number of poses (default 300)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the garment's poses and folds (default 0)")
    _add_overwrite(p)
    _add_json(p)

    p = sub.add_parser("import", help="OBJ/PLY sequences (same connectivity) -> dataset")
    p.add_argument("out", type=Path, help="dataset directory to write")
    p.add_argument("--gt", required=True, help="glob of ground-truth meshes (sorted order = pose order)")
    p.add_argument("--inferred", required=True, help="glob of inferred meshes, paired in sorted order")
    p.add_argument("--poses", type=Path, help="pose vectors: .npy (K,P) or text rows")
    p.add_argument("--name", help="dataset name (default: the folder name)")
    _add_overwrite(p)
    _add_progress(p)

    p = sub.add_parser("render", help="textured PNGs of gt and inferred per camera")
    p.add_argument("dataset", type=Path, help="mvtex dataset directory")
    p.add_argument("--rig", required=True, help="rig YAML, or a built-in rig name (stereo, square4, trapezoid12)")
    p.add_argument("--pose", type=int, required=True, help="dataset pose index")
    p.add_argument("--out", type=Path, required=True, help="output directory")
    p.add_argument("--texcoords", type=Path, help="texcoord set: draw the inferred mesh with its texcoords")
    p.add_argument("--raster", action="store_true", help="also write raster dumps (tri_id, bary, depth, uv)")
    p.add_argument("--cameras", help="comma-separated camera names (default: all)")
    _add_overwrite(p)
    _add_progress(p)

    p = sub.add_parser("slide", help="texture sliding over a dataset and a rig -> texcoord set")
    p.add_argument("dataset", type=Path, help="mvtex dataset directory")
    p.add_argument("--rig", required=True, help="rig YAML, or a built-in rig name (stereo, square4, trapezoid12)")
    p.add_argument("--out", type=Path, required=True, help="output directory")
    p.add_argument("--poses", default="all", help="all, train, val, test, a:b or 3,5,7 (default all)")
    p.add_argument("--subdiv", type=int, default=1, choices=(0, 1, 2), help="midpoint subdivisions of the inferred mesh (default 1)")
    p.add_argument("--fill", default="harmonic", choices=("harmonic", "fmm"), help="how unassigned vertices are filled (default harmonic)")
    p.add_argument("--max-displacement", type=float, help="unassign vertices with |d| above this (uv units)")
    p.add_argument("--cameras", help="comma-separated camera names (default: all)")
    _add_workers(p, "default: one per core for long runs, else 1")
    _add_overwrite(p)
    _add_progress(p)

    p = sub.add_parser("eval", help="per-pixel texture-coordinate error: baseline vs a texcoord set")
    p.add_argument("dataset", type=Path, help="mvtex dataset directory")
    p.add_argument("--rig", required=True, help="rig YAML, or a built-in rig name (stereo, square4, trapezoid12)")
    p.add_argument("--texcoords", type=Path, required=True, help="texcoord set directory")
    p.add_argument("--poses", help="pose SPEC (default: the texcoord set's poses)")
    p.add_argument("--heatmaps", type=Path, help="write error heatmaps here")
    _add_workers(p, "default 1")
    _add_overwrite(p)
    _add_json(p)
    _add_progress(p)

    p = sub.add_parser("triangulate", help="multi-view reconstruction of one pose -> PLY + COLMAP model")
    p.add_argument("dataset", type=Path, help="mvtex dataset directory")
    p.add_argument("--rig", required=True, help="rig YAML, or a built-in rig name (stereo, square4, trapezoid12)")
    p.add_argument("--texcoords", type=Path, required=True, help="texcoord set directory")
    p.add_argument("--pose", type=int, required=True, help="dataset pose index")
    p.add_argument("--out", type=Path, required=True, help="output directory")
    p.add_argument("--smooth", action="store_true", help="smooth the reconstructed displacement (noisy inputs)")
    p.add_argument("--max-reprojection-px", type=float, default=2.0, help="reject points above this (default 2 px)")
    p.add_argument("--max-surface-distance", type=float, default=0.05,
                   help="reject points farther than this from the inferred surface (default 0.05 m)")
    _add_overwrite(p)
    _add_json(p)
    _add_progress(p)

    p = sub.add_parser("train", help="train the texture sliding network of one camera")
    p.add_argument("dataset", type=Path, help="mvtex dataset directory")
    p.add_argument("--texcoords", type=Path, required=True, help="texcoord set directory")
    p.add_argument("--camera", required=True, help="the camera of the texcoord set to learn")
    p.add_argument("--out", type=Path, required=True, help="output directory")
    p.add_argument("--epochs", type=int, help="training epochs (at least 1; default: the training default)")
    p.add_argument("--resolution", type=int, help=f"atlas image size, a power of two in 8..{MAX_RESOLUTION} (default: 512 on GPU, 64 on CPU)")
    p.add_argument("--device", default=None, help="cpu, cuda, cuda:0 ... (default: cuda if available)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the initial weights and batches (default 0)")
    _add_overwrite(p)
    _add_json(p)
    _add_progress(p)

    p = sub.add_parser("predict", help="camera networks -> texcoord set")
    p.add_argument("dataset", type=Path, help="mvtex dataset directory")
    p.add_argument("--model", type=Path, action="append", required=True, help="a trained model (repeat per camera)")
    p.add_argument("--out", type=Path, required=True, help="output directory")
    p.add_argument("--poses", default="all", help="pose SPEC (default all)")
    _add_overwrite(p)
    _add_progress(p)

    p = sub.add_parser("bench", help="throughput: raster vs ray-cast sliding, and eval")
    p.add_argument("dataset", type=Path, help="mvtex dataset directory")
    p.add_argument("--rig", required=True, help="rig YAML, or a built-in rig name (stereo, square4, trapezoid12)")
    p.add_argument("--poses", default="0:20", help="poses to time (default 0:20)")
    p.add_argument("--subdiv", type=int, default=1, choices=(0, 1, 2), help="midpoint subdivisions of the inferred mesh (default 1)")
    p.add_argument("--workers", type=int, default=2, help="worker processes for the parallel measurement (default 2)")
    _add_json(p)
    _add_progress(p)

    p = sub.add_parser("demo", help="the whole pipeline on the built-in garment")
    p.add_argument("--out", type=Path, default=Path("mvtex-demo"), help="output directory (default mvtex-demo)")
    p.add_argument("--poses", type=int, default=120, help="poses to synthesize (default 120)")
    p.add_argument("--epochs", type=int, help="TSNN epochs (default: the training default)")
    _add_overwrite(p)
    _add_json(p)
    _add_progress(p)
    return parser


MAX_RESOLUTION = 4096
_DEVICE = re.compile(r"^(auto|cpu|mps|cuda(:\d{1,3})?)$")


def _cameras(value: str | None) -> list[str] | None:
    return [c.strip() for c in value.split(",") if c.strip()] if value else None


def _positive(value: float | None, option: str, *, allow_none: bool = False) -> None:
    """InputError unless value is a finite number > 0."""
    if value is None and allow_none:
        return
    if value is None or not math.isfinite(value) or value <= 0:
        raise InputError(None, f"{option} must be a finite number > 0 (got {value})")


def _at_least(value: int | None, option: str, low: int) -> None:
    if value is not None and value < low:
        raise InputError(None, f"{option} must be at least {low} (got {value})")


def _check_workers(args) -> None:
    _at_least(args.workers, "--workers", 1)
    if args.scheduler is not None and not args.scheduler.strip():
        raise InputError(None, "--scheduler needs an address such as tcp://host:8786")


def _check_pose(dataset, pose: int) -> None:
    if not 0 <= pose < dataset.num_poses:
        raise InputError(dataset.path, f"pose {pose} out of range (dataset has {dataset.num_poses} poses)")


def _check_cameras_see(rig, rig_path, dataset, poses) -> None:
    """Refuse a camera that sees no vertex of the inferred mesh at the first selected pose."""
    positions = dataset.inferred[int(poses[0]) if poses else 0]
    blind = [cam.name for cam in rig if not cam.sees(positions)]
    if blind:
        raise InputError(rig_path, f"camera {blind[0]!r} sees nothing of the mesh of {dataset.path} "
                         f"(pose {int(poses[0]) if poses else 0}): check its R, t and K")


def _load_rig(spec: str):
    """The rig and its path; cameras with distortion are refused (every command renders)."""
    from .camera import load_rig, resolve_rig
    from .render import check_renderable

    path = resolve_rig(spec)
    rig = load_rig(path)
    check_renderable(rig, path)
    return rig, str(path)


def _emit(args, result: dict, text: str) -> None:
    if getattr(args, "json", False):
        print(dumps_strict(result))
    else:
        print(text)


def _output(args, command: str, path: Path | None = None, in_place: bool = False):
    """Claim the command's output directory (see `mvtex.io.claim_output`)."""
    return claim_output(path if path is not None else args.out, command, overwrite=args.overwrite, in_place=in_place)


def cmd_synth(args) -> dict:
    from .synth import SynthOptions, write_synth

    if args.poses < 10:
        raise InputError(None, f"--poses must be at least 10 (got {args.poses})")
    with _output(args, "synth"):
        stats = write_synth(args.out, SynthOptions(num_poses=args.poses, seed=args.seed))
    _emit(args, stats, f"wrote {args.out}: " + ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                                                           for k, v in stats.items()))
    return stats


def cmd_import(args) -> None:
    from .dataset import import_sequences

    with _output(args, "import"):
        path = import_sequences(args.out, args.gt, args.inferred, args.poses, name=args.name,
                                progress=not args.quiet)
    print(f"wrote {path}")


def cmd_render(args) -> None:
    from .dataset import load_dataset
    from .render import render_pose
    from .texcoords import open_texcoords

    dataset = load_dataset(args.dataset)
    rig, rig_path = _load_rig(args.rig)
    rig = rig.select(_cameras(args.cameras), rig_path)
    tc = open_texcoords(args.texcoords, dataset.num_vertices) if args.texcoords else None
    _check_pose(dataset, args.pose)
    _check_cameras_see(rig, rig_path, dataset, [args.pose])
    with _output(args, "render", in_place=True):
        summary = render_pose(dataset, rig, args.pose, args.out, texcoords=tc, raster=args.raster,
                              rig_path=rig_path, progress=not args.quiet)
    print(f"wrote {len(summary['files'])} files to {args.out}")


def cmd_slide(args) -> None:
    from .dataset import load_dataset
    from .sliding import SlideOptions, slide_dataset

    _check_workers(args)
    _positive(args.max_displacement, "--max-displacement", allow_none=True)
    dataset = load_dataset(args.dataset)
    rig, rig_path = _load_rig(args.rig)
    rig = rig.select(_cameras(args.cameras), rig_path)
    options = SlideOptions(subdiv=args.subdiv, fill=args.fill, max_displacement=args.max_displacement)
    poses = dataset.select(args.poses)
    _check_cameras_see(rig, rig_path, dataset, poses)
    with _output(args, "slide"):
        out = slide_dataset(dataset, rig, args.out, poses=poses, options=options,
                            workers=args.workers, scheduler=args.scheduler, progress=not args.quiet)
    print(f"wrote {out}")


def cmd_eval(args) -> dict:
    from .dataset import load_dataset
    from .metrics import evaluate
    from .texcoords import open_texcoords

    _check_workers(args)
    dataset = load_dataset(args.dataset)
    rig, rig_path = _load_rig(args.rig)
    tc = open_texcoords(args.texcoords, dataset.num_vertices, num_poses=dataset.num_poses)
    poses = dataset.select(args.poses) if args.poses else None
    rig = rig.select(tc.cameras, rig_path)
    _check_cameras_see(rig, rig_path, dataset, poses or tc.poses)
    with _output(args, "eval", args.heatmaps, in_place=True) if args.heatmaps else contextlib.nullcontext():
        result = evaluate(dataset, rig, tc, poses=poses, heatmaps=args.heatmaps,
                          progress=not args.quiet, workers=args.workers or 1, scheduler=args.scheduler)
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

    _positive(args.max_reprojection_px, "--max-reprojection-px")
    _positive(args.max_surface_distance, "--max-surface-distance")
    dataset = load_dataset(args.dataset)
    rig, rig_path = _load_rig(args.rig)
    tc = open_texcoords(args.texcoords, dataset.num_vertices, num_poses=dataset.num_poses)
    _check_pose(dataset, args.pose)
    rig = rig.select(tc.cameras, rig_path)
    _check_cameras_see(rig, rig_path, dataset, [args.pose])
    with _output(args, "triangulate"):
        result = triangulate_pose(dataset, rig, tc, args.pose, args.out,
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
    from .tsnn.train import TrainOptions, train_camera

    _at_least(args.epochs, "--epochs", 1)
    if args.resolution is not None and (args.resolution < 8 or args.resolution > MAX_RESOLUTION
                                        or args.resolution & (args.resolution - 1)):
        raise InputError(None, f"--resolution must be a power of two in 8..{MAX_RESOLUTION} (got {args.resolution})")
    if args.device is not None and not _DEVICE.match(args.device):
        raise InputError(None, f"--device must be auto, cpu, mps, cuda or cuda:N (got {args.device!r})")
    dataset = load_dataset(args.dataset)
    tc = open_texcoords(args.texcoords, dataset.num_vertices, num_poses=dataset.num_poses)
    options = TrainOptions(seed=args.seed)
    changes = {k: getattr(args, k) for k in ("epochs", "resolution", "device") if getattr(args, k) is not None}
    options = replace(options, **changes)
    with _output(args, "train"):
        result = train_camera(dataset, tc, args.camera, args.out, options, progress=not args.quiet)
    _emit(args, result, f"wrote {args.out}")
    return result


def cmd_predict(args) -> None:
    from .dataset import load_dataset
    from .tsnn.predict import predict

    dataset = load_dataset(args.dataset)
    poses = dataset.select(args.poses)
    with _output(args, "predict"):
        out = predict(dataset, args.model, args.out, poses=poses, progress=not args.quiet)
    print(f"wrote {out}")


def cmd_bench(args) -> dict:
    from .bench import run_bench
    from .dataset import load_dataset

    _at_least(args.workers, "--workers", 1)
    dataset = load_dataset(args.dataset)
    rig, rig_path = _load_rig(args.rig)
    poses = dataset.select(args.poses)
    _check_cameras_see(rig, rig_path, dataset, poses)
    result = run_bench(dataset, rig, poses=poses, subdiv=args.subdiv, workers=args.workers,
                       progress=not args.quiet)
    _emit(args, result, dumps_strict(result, indent=2))
    return result


def cmd_demo(args) -> dict:
    from .demo import DemoOptions, run_demo

    _at_least(args.poses, "--poses", 10)
    _at_least(args.epochs, "--epochs", 1)
    options = DemoOptions(num_poses=args.poses, epochs=args.epochs)
    with _output(args, "demo", in_place=True):
        result = run_demo(args.out, options, progress=not args.quiet)
    _emit(args, result, result.get("summary_text", dumps_strict(result, indent=2)))
    return result


COMMANDS = {"synth": cmd_synth, "import": cmd_import, "render": cmd_render, "slide": cmd_slide, "eval": cmd_eval,
            "triangulate": cmd_triangulate, "train": cmd_train, "predict": cmd_predict, "bench": cmd_bench,
            "demo": cmd_demo}


def main(argv: Sequence[str] | None = None) -> int:
    """Run one command. Returns 0 on success, 2 on bad usage or bad input (one line on
    stderr naming the file and the problem), 130 when interrupted; any other failure is a
    bug and propagates with its traceback (exit 1 from the `mvtex` script)."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exit_:  # argparse: 2 on bad usage, 0 on --help
        return int(exit_.code or 0)
    try:
        COMMANDS[args.command](args)
    except InputError as err:
        return _fail(args.command, str(err))
    except OSError as err:
        # The file system refused a user's path (permissions, a full disk, a file where a
        # folder should be): a one-line error, not a bug. Other OSErrors carry no filename.
        if err.filename is None:
            raise
        return _fail(args.command, InputError(err.filename, err.strerror or str(err)).args[0])
    except KeyboardInterrupt:
        print(f"mvtex {args.command}: interrupted (rerun the same command to resume where supported)", file=sys.stderr)
        return 130
    return 0


def _fail(command: str, message: str) -> int:
    print(f"mvtex {command}: error: {message}", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
