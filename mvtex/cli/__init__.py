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

from mvtex import __version__
from mvtex.util.errors import InputError
from mvtex.util.files import dumps_strict
from mvtex.util.output import claim_output


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
    parser.add_argument("--version", action="version", version=f"mvtex {__version__}",
                        help="print the version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True,
                                help="one of these; `mvtex COMMAND --help` lists its options")

    p = sub.add_parser("synth", help="write a built-in garment dataset (shirt or skirt)")
    p.add_argument("out", type=Path, help="dataset directory to write")
    p.add_argument("--poses", type=int, default=300, help="number of poses (default 300)")
    p.add_argument("--seed", type=int, default=0, help="random seed of poses and folds (default 0)")
    p.add_argument("--garment", default="shirt", choices=("shirt", "skirt"),
                   help="shirt: torso tube with bend/twist folds; skirt: flared skirt with hem flutes (default shirt)")
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
    p.add_argument("dataset", type=Path, help="dataset directory")
    p.add_argument("--rig", required=True, help="rig YAML, or a built-in rig name (stereo, square4, trapezoid12)")
    p.add_argument("--pose", type=int, required=True, help="pose index to render")
    p.add_argument("--out", type=Path, required=True, help="output directory (PNGs, render.json)")
    p.add_argument("--texcoords", type=Path, help="texcoord set: draw the inferred mesh with its texcoords")
    p.add_argument("--raster", action="store_true", help="also write raster dumps (tri_id, bary, depth, uv)")
    p.add_argument("--cameras", help="comma-separated camera names (default: all)")
    _add_overwrite(p)
    _add_progress(p)

    p = sub.add_parser("slide", help="texture sliding over a dataset and a rig -> texcoord set")
    p.add_argument("dataset", type=Path, help="dataset directory")
    p.add_argument("--rig", required=True, help="rig YAML, or a built-in rig name (stereo, square4, trapezoid12)")
    p.add_argument("--out", type=Path, required=True,
                   help="texcoord set directory to write (resumable: rerun to continue)")
    p.add_argument("--poses", default="all", help="all, train, val, test, a:b or 3,5,7 (default all)")
    p.add_argument("--subdiv", type=int, default=1, choices=(0, 1, 2),
                   help="midpoint subdivision levels of the inferred mesh (default 1)")
    p.add_argument("--fill", default="harmonic", choices=("harmonic", "fmm"),
                   help="fill of unassigned vertices: harmonic (cotangent Laplace) or fmm (default harmonic)")
    p.add_argument("--max-displacement", type=float, help="unassign vertices with |d| above this (uv units)")
    p.add_argument("--break-ratio", metavar="R|off",
                   help="break edges whose |dT_N| exceeds R x their |dT_G| (R > 1); off = the paper's plain "
                        "method (default: SlideOptions.break_ratio)")
    p.add_argument("--radius", type=int, help="candidate window half-size in pixels, 1 = 3x3 (default 1)")
    p.add_argument("--depth-tolerance", type=float,
                   help="relative tolerance of the vertex depth test (default: SlideOptions.depth_tolerance)")
    p.add_argument("--cross-chart", choices=("on", "off"),
                   help="keep hits on another UV chart than the vertex's own (default: SlideOptions.cross_chart)")
    p.add_argument("--cameras", help="comma-separated camera names (default: all)")
    _add_workers(p, "default: one per core for long runs, else 1")
    _add_overwrite(p)
    _add_progress(p)

    p = sub.add_parser("eval", help="material error (mm) and per-pixel texture-coordinate error: baseline vs a texcoord set")
    p.add_argument("dataset", type=Path, help="dataset directory")
    p.add_argument("--rig", required=True,
                   help="rig YAML or built-in rig name; its cameras that are in the texcoord set are evaluated")
    p.add_argument("--texcoords", type=Path, required=True, help="texcoord set to evaluate")
    p.add_argument("--poses", help="pose SPEC (default: the texcoord set's poses)")
    p.add_argument("--heatmaps", type=Path, help="write error heatmaps here")
    _add_workers(p, "default 1")
    _add_overwrite(p)
    _add_json(p)
    _add_progress(p)

    p = sub.add_parser("triangulate", help="multi-view reconstruction of one pose -> PLY + COLMAP model")
    p.add_argument("dataset", type=Path, help="dataset directory")
    p.add_argument("--rig", required=True, help="rig YAML or built-in rig name (e.g. trapezoid12)")
    p.add_argument("--texcoords", type=Path, required=True, help="texcoord set directory (from slide or predict)")
    p.add_argument("--pose", type=int, required=True, help="dataset pose index (one of the texcoord set's poses)")
    p.add_argument("--out", type=Path, required=True, help="output directory (PLY, COLMAP model, pictures, report)")
    p.add_argument("--smooth", action="store_true", help="smooth the reconstructed displacement (noisy inputs)")
    p.add_argument("--max-reprojection-px", type=float, default=2.0, help="reject points above this (default 2 px)")
    p.add_argument("--max-surface-distance", type=float, default=0.05,
                   help="reject points farther than this from the inferred surface (default 0.05 m)")
    p.add_argument("--engine", choices=("mvtex", "pycolmap"), default="mvtex",
                   help="who triangulates the tracks: mvtex (vectorised DLT + Gauss-Newton, faster) or pycolmap "
                        "(COLMAP multi-view triangulation + points-only bundle adjustment); same points (default mvtex)")
    _add_overwrite(p)
    _add_json(p)
    _add_progress(p)

    p = sub.add_parser("train", help="train a texture sliding network (one camera, or all conditioned on the camera)")
    p.add_argument("dataset", type=Path, help="dataset directory")
    p.add_argument("--texcoords", type=Path, required=True, help="texcoord set with the training targets")
    p.add_argument("--camera", help="train this camera's network (default: one network for every camera of "
                   "--texcoords, conditioned on the camera); A,B,...: one model per camera, OUT/<camera>, "
                   "trained side by side with --workers or --scheduler")
    p.add_argument("--rig", help="rig of the texcoord set's cameras (needed without --camera: builtin name or "
                   "rig.yaml; default TEXCOORDS/rig.yaml)")
    p.add_argument("--out", type=Path, required=True, help="model directory to write")
    p.add_argument("--arch", choices=("gp", "unet", "paper"),
                   help="gp: Gaussian processes of the pose on the principal components of d, per camera (default "
                   "with --camera; the most accurate from 120 to 960 poses); unet: geometry images of the inferred "
                   "mesh + pose, any camera (default without --camera); paper: the paper's pose-only decoder")
    p.add_argument("--components", type=int, help="principal components of d modelled by gp (default 32)")
    p.add_argument("--epochs", type=int, help="most training epochs of unet and paper (default 60)")
    p.add_argument("--resolution", type=int,
                   help=f"atlas image size, a power of two in 8..{MAX_RESOLUTION} (default: 512 on GPU, 64 on CPU)")
    p.add_argument("--device", default=None, help="cpu, cuda, cuda:0 ... (default: cuda if available)")
    p.add_argument("--seed", type=int, default=0, help="seed of initialisation and batch order (default 0)")
    _add_workers(p, "default 1; with several --camera names")
    _add_overwrite(p)
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
    _add_overwrite(p)
    _add_progress(p)

    # -- novel views and stereo previews ----------------------------------------------------
    p = sub.add_parser("views", help="texcoords of novel views between array cameras -> texcoord set + rig.yaml")
    p.add_argument("dataset", type=Path, help="dataset directory")
    p.add_argument("--rig", required=True, help="the array's rig YAML or built-in rig name")
    p.add_argument("--texcoords", type=Path, required=True, help="the array's texcoord set (slide or predict)")
    p.add_argument("--out", type=Path, required=True, help="texcoord set to write (with OUT/rig.yaml)")
    p.add_argument("--poses", help="pose SPEC (default: the texcoord set's poses)")
    p.add_argument("--method", default="reconstruct", choices=("blend", "reconstruct"),
                   help="blend the array's texcoords (the paper) or slide against the reconstruction "
                        "(default reconstruct)")
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--weights", help='one view: "A=0.3,B=0.7" (weights >= 0 summing to 1)')
    g.add_argument("--between", help="A,B: --steps views evenly from A to B, both ends included")
    g.add_argument("--grid", help="A,B,C,D: --steps x --steps views bilinear over a 2x2 array (row-major from A)")
    p.add_argument("--steps", type=int, help="number of views along --between, per side of --grid")
    p.add_argument("--name", default="view", help='name of the --weights view (default "view")')
    p.add_argument("--plot", type=Path, help="also write a PNG of SqrtMSE against the path (needs gt): "
                   "baseline, this method and TS computed directly at each view")
    _add_workers(p, "default 1")
    _add_overwrite(p)
    _add_json(p)
    _add_progress(p)

    p = sub.add_parser("preview", help="stereo AR preview: left/right eye renders, anaglyph, SSIM/PSNR vs gt")
    p.add_argument("dataset", type=Path, help="dataset directory")
    p.add_argument("--rig", required=True, help="the array's rig YAML or built-in rig name")
    p.add_argument("--texcoords", type=Path, required=True, help="the array's texcoord set")
    p.add_argument("--pose", type=int, required=True, help="dataset pose index (one of the texcoord set's poses)")
    p.add_argument("--out", type=Path, required=True,
                   help="output folder: stereo.png, anaglyph.png, comparison.png, preview.json")
    p.add_argument("--weights", help='viewpoint "A=0.5,B=0.5" (default: equal weights over the rig\'s cameras)')
    p.add_argument("--ipd", type=float, default=0.064, help="distance between the eyes in meters (default 0.064)")
    p.add_argument("--method", default="reconstruct", choices=("blend", "reconstruct"),
                   help="how each eye's texcoords are computed (as in views; default reconstruct)")
    p.add_argument("--path", action="store_true", help="also write path.gif: the viewpoint moving across the array")
    _add_overwrite(p)
    _add_json(p)
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
    p.add_argument("--out", type=Path, default=Path("mvtex-demo"),
                   help="output directory (default mvtex-demo; rerun to resume)")
    p.add_argument("--poses", type=int, default=120, help="poses to synthesize (default 120)")
    p.add_argument("--epochs", type=int, help="kept for scripts; the demo trains the per-camera default gp, which has no epochs")
    _add_overwrite(p)
    _add_json(p)
    _add_progress(p)
    _add_calibration_parsers(sub)
    return parser


# `mvtex.tsnn.train.MAX_RESOLUTION`, repeated here so that `mvtex --help` does not import the
# training module (tests/test_tsnn.py holds the two equal).
MAX_RESOLUTION = 2048
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


def _load_rig(spec: str, pinhole: bool = True):
    """The rig and its path; with `pinhole` (commands that render) cameras with distortion
    are refused."""
    from mvtex.data.rig import load_rig, resolve_rig

    path = resolve_rig(spec)
    rig = load_rig(path)
    if pinhole:
        for camera in rig:
            camera.require_pinhole(path)
    return rig, str(path)


def _emit(args, result: dict, text: str) -> None:
    if getattr(args, "json", False):
        print(dumps_strict(result))
    else:
        print(text)


def _output(args, command: str, path: Path | None = None, in_place: bool = False):
    """Claim the command's output directory (see `mvtex.util.output.claim_output`)."""
    return claim_output(path if path is not None else args.out, command, overwrite=args.overwrite, in_place=in_place)


def cmd_synth(args) -> dict:
    from mvtex.synth.generate import SynthOptions, write_synth

    if args.poses < 10:
        raise InputError(None, f"--poses must be at least 10 (got {args.poses})")
    with _output(args, "synth"):
        stats = write_synth(args.out, SynthOptions(num_poses=args.poses, seed=args.seed, garment=args.garment))
    _emit(args, stats, f"wrote {args.out}: " + ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                                                           for k, v in stats.items()))
    return stats


def cmd_import(args) -> None:
    from mvtex.data.importer import import_sequences

    with _output(args, "import"):
        path = import_sequences(args.out, args.gt, args.inferred, args.poses, name=args.name,
                                progress=not args.quiet)
    print(f"wrote {path}")


def cmd_render(args) -> None:
    from mvtex.data.dataset import load_dataset
    from mvtex.data.texcoords import open_texcoords
    from mvtex.render.pose import render_pose

    dataset = load_dataset(args.dataset)
    rig, rig_path = _load_rig(args.rig)
    rig = rig.select(_cameras(args.cameras), rig_path)
    tc = open_texcoords(args.texcoords, dataset.num_vertices) if args.texcoords else None
    _check_pose(dataset, args.pose)
    _check_cameras_see(rig, rig_path, dataset, [args.pose])
    with _output(args, "render", in_place=True):
        summary = render_pose(dataset, rig, args.pose, args.out, texcoord_set=tc, raster=args.raster,
                              rig_path=rig_path, progress=not args.quiet)
    print(f"wrote {len(summary['files'])} files to {args.out}")


def slide_option_flags(args) -> dict:
    """SlideOptions fields set by `slide`'s optional flags (unset flags keep the defaults)."""
    changes = {}
    if args.break_ratio is not None:
        if args.break_ratio.strip().lower() == "off":
            changes["break_ratio"] = None
        else:
            try:
                changes["break_ratio"] = float(args.break_ratio)
            except ValueError:
                raise InputError(None, f"--break-ratio must be a number > 1 or 'off' "
                                       f"(got {args.break_ratio!r})") from None
    if args.radius is not None:
        changes["radius"] = args.radius
    if args.depth_tolerance is not None:
        changes["depth_tolerance"] = args.depth_tolerance
    if args.cross_chart is not None:
        changes["cross_chart"] = args.cross_chart == "on"
    return changes


def cmd_slide(args) -> None:
    from mvtex.data.dataset import load_dataset
    from mvtex.sliding.dataset import slide_dataset
    from mvtex.sliding.options import SlideOptions

    _check_workers(args)
    _positive(args.max_displacement, "--max-displacement", allow_none=True)
    dataset = load_dataset(args.dataset)
    rig, rig_path = _load_rig(args.rig)
    rig = rig.select(_cameras(args.cameras), rig_path)
    try:
        options = SlideOptions(subdiv=args.subdiv, fill=args.fill, max_displacement=args.max_displacement,
                               **slide_option_flags(args))
    except ValueError as err:
        raise InputError(None, str(err)) from None
    poses = dataset.select(args.poses)
    _check_cameras_see(rig, rig_path, dataset, poses)
    with _output(args, "slide"):
        out = slide_dataset(dataset, rig, args.out, poses=poses, options=options,
                            workers=args.workers, scheduler=args.scheduler, progress=not args.quiet)
    print(f"wrote {out}")


def cmd_eval(args) -> dict:
    from mvtex.data.dataset import load_dataset
    from mvtex.data.texcoords import open_texcoords
    from mvtex.evaluation.evaluate import evaluate

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
    s, c, m = result["sqrt_mse"], result["sqrt_mse_same_chart"], result["material_rmse_m"]
    material = (f"material error inferred {m['inferred']['mean']*1e3:.2f} ± {m['inferred']['std']*1e3:.2f} mm, "
                f"texcoords {m['texcoords']['mean']*1e3:.2f} ± {m['texcoords']['std']*1e3:.2f} mm, "
                f"ratio {result['ratio_material']:.2f}; " if m is not None else "")
    _emit(args, result, f"{result['num_images']} images: {material}SqrtMSE inferred {s['inferred']['mean']*1e3:.3f} ± "
          f"{s['inferred']['std']*1e3:.3f} e-3, texcoords {s['texcoords']['mean']*1e3:.3f} ± "
          f"{s['texcoords']['std']*1e3:.3f} e-3, ratio {result['ratio']:.2f}; same-chart pixels: "
          f"{c['inferred']['mean']*1e3:.3f} -> {c['texcoords']['mean']*1e3:.3f} e-3, ratio {result['ratio_same_chart']:.2f}")
    return result


def cmd_triangulate(args) -> dict:
    from mvtex.data.dataset import load_dataset
    from mvtex.data.texcoords import open_texcoords
    from mvtex.recon.pose import triangulate_pose
    from mvtex.recon.triangulate import ReconOptions

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
                                               max_surface_distance_m=args.max_surface_distance,
                                               engine=args.engine),
                                  progress=not args.quiet)
    _emit(args, result, f"pose {result['pose']}: {result['num_triangulated']}/{result['num_vertices']} vertices "
          f"triangulated; RMSE inferred {result['rmse_m']['inferred']*1e3:.2f} mm -> reconstructed "
          f"{result['rmse_m']['reconstructed']*1e3:.2f} mm; wrote {args.out}")
    return result


def cmd_train(args) -> dict:
    from dataclasses import replace

    from mvtex.data.dataset import load_dataset
    from mvtex.data.texcoords import open_texcoords
    from mvtex.tsnn.train import TrainOptions, train

    _at_least(args.epochs, "--epochs", 1)
    if args.resolution is not None and (args.resolution < 8 or args.resolution > MAX_RESOLUTION
                                        or args.resolution & (args.resolution - 1)):
        raise InputError(None, f"--resolution must be a power of two in 8..{MAX_RESOLUTION} (got {args.resolution})")
    if args.device is not None and not _DEVICE.match(args.device):
        raise InputError(None, f"--device must be auto, cpu, mps, cuda or cuda:N (got {args.device!r})")
    dataset = load_dataset(args.dataset)
    tc = open_texcoords(args.texcoords, dataset.num_vertices, num_poses=dataset.num_poses)
    options = TrainOptions(seed=args.seed, arch=args.arch)
    if args.components is not None and not 1 <= args.components <= 256:
        raise InputError(None, f"--components must be in 1..256 (got {args.components})")
    changes = {k: getattr(args, k) for k in ("epochs", "resolution", "device", "components")
               if getattr(args, k) is not None}
    options = replace(options, **changes)
    _check_workers(args)
    cameras = _cameras(args.camera) if args.camera is not None else None
    if args.camera is not None and not cameras:
        raise InputError(None, f"--camera needs a camera name or a comma-separated list (got {args.camera!r})")
    if (args.workers is not None or args.scheduler is not None) and (cameras is None or len(cameras) < 2):
        raise InputError(None, "--workers and --scheduler train several cameras side by side: "
                         "give --camera A,B,...")
    if cameras is not None and len(cameras) > 1:
        from mvtex.tsnn.cameras import train_cameras

        with _output(args, "train", in_place=True):
            try:
                result = train_cameras(dataset, tc, cameras, args.out, options, workers=args.workers or 1,
                                       scheduler=args.scheduler, progress=not args.quiet)
            except ValueError as err:
                raise InputError(None, str(err)) from None
        kept = f" (kept from an earlier run with the same inputs: {', '.join(result['kept'])})" if result["kept"] else ""
        _emit(args, result, f"wrote {len(cameras)} models ({result['arch']}) to {args.out}/<camera>: "
              f"{', '.join(cameras)}{kept}")
        return result
    rig = None
    if args.camera is None:
        if args.rig is None and not (args.texcoords / "rig.yaml").is_file():
            raise InputError(args.texcoords, "one network for every camera needs their rig: give --rig "
                             "(or --camera NAME for one camera's network)")
        rig, _ = _load_rig(args.rig or str(args.texcoords / "rig.yaml"))
    with _output(args, "train"):
        try:
            result = train(dataset, tc, args.out, camera=cameras[0] if cameras else None, rig=rig,
                           options=options, progress=not args.quiet)
        except ValueError as err:
            raise InputError(None, str(err)) from None
    _emit(args, result, f"wrote {args.out} ({result['arch']}, {', '.join(result['cameras'])})")
    return result


def cmd_predict(args) -> None:
    from mvtex.data.dataset import load_dataset
    from mvtex.tsnn.predict import predict

    dataset = load_dataset(args.dataset)
    rig = _load_rig(args.rig)[0] if args.rig else None
    poses = dataset.select(args.poses)
    with _output(args, "predict"):
        out = predict(dataset, args.model, args.out, poses=poses, rig=rig, progress=not args.quiet)
    print(f"wrote {out}")


# -- novel views and stereo previews ------------------------------------------------------------

def _view_weights(args, rig, rig_path):
    from mvtex.views.cameras import between_weights, grid_weights, parse_weights, view_names

    if args.weights is not None:
        if args.steps is not None:
            raise InputError(None, "--steps goes with --between or --grid, not --weights")
        return [parse_weights(args.weights)], [args.name]
    if args.steps is None:
        raise InputError(None, "--between and --grid need --steps N")
    corners = _cameras(args.between if args.between is not None else args.grid) or []
    if len(corners) != (2 if args.between is not None else 4):
        raise InputError(None, f"--{'between' if args.between is not None else 'grid'} needs "
                         f"{2 if args.between is not None else 4} comma-separated camera names, got {corners}")
    rig.select(corners, rig_path)
    weights = between_weights(*corners, args.steps) if len(corners) == 2 else grid_weights(*corners, args.steps)
    return weights, view_names(len(weights))


def cmd_views(args) -> dict:
    from mvtex.data.dataset import load_dataset
    from mvtex.data.texcoords import open_texcoords
    from mvtex.views.novel import novel_views
    from mvtex.views.synthesizer import ViewOptions

    dataset = load_dataset(args.dataset)
    rig, rig_path = _load_rig(args.rig)
    tc = open_texcoords(args.texcoords, dataset.num_vertices, num_poses=dataset.num_poses)
    weights, names = _view_weights(args, rig, rig_path)
    poses = dataset.select(args.poses) if args.poses else None
    if args.plot is not None and args.weights is not None:
        raise InputError(args.plot, "--plot needs the views of --between or --grid")
    _check_workers(args)
    with _output(args, "views"):
        result = novel_views(dataset, rig, tc, args.out, weights, names, poses=poses,
                             options=ViewOptions(method=args.method), rig_source=rig_path, progress=not args.quiet,
                             workers=args.workers or 1, scheduler=args.scheduler)
    if args.plot is not None:
        from mvtex.views.measure import path_plot

        result["measured"] = path_plot(dataset, rig, tc, weights, names, args.plot, poses=poses,
                                       progress=not args.quiet)
    _emit(args, result, f"wrote {len(names)} view(s) x {len(result['poses'])} pose(s) ({args.method}) to {args.out}")
    return result


def cmd_preview(args) -> dict:
    from mvtex.data.dataset import load_dataset
    from mvtex.data.texcoords import open_texcoords
    from mvtex.views.cameras import parse_weights
    from mvtex.views.preview import PreviewOptions, stereo_preview

    dataset = load_dataset(args.dataset)
    rig, rig_path = _load_rig(args.rig)
    tc = open_texcoords(args.texcoords, dataset.num_vertices, num_poses=dataset.num_poses)
    weights = parse_weights(args.weights) if args.weights else None
    if not (args.ipd >= 0 and args.ipd < 10):
        raise InputError(None, f"--ipd must be in [0, 10) meters, got {args.ipd}")
    with _output(args, "preview"):
        result = stereo_preview(dataset, rig, tc, args.pose, args.out, weights=weights,
                                options=PreviewOptions(ipd=args.ipd, method=args.method, path=args.path),
                                rig_source=rig_path, progress=not args.quiet, overwrite=args.overwrite)
    eyes = result["eyes"]
    _emit(args, result, f"pose {result['pose']}: SSIM inferred -> texcoords: left {eyes['left']['ssim']['inferred']:.3f}"
          f" -> {eyes['left']['ssim']['texcoords']:.3f}, right {eyes['right']['ssim']['inferred']:.3f} -> "
          f"{eyes['right']['ssim']['texcoords']:.3f}; wrote {args.out}")
    return result


def cmd_bench(args) -> dict:
    from mvtex.apps.bench import run_bench
    from mvtex.data.dataset import load_dataset

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
    from mvtex.apps.demo import DemoOptions, run_demo

    _at_least(args.poses, "--poses", 10)
    _at_least(args.epochs, "--epochs", 1)
    options = DemoOptions(num_poses=args.poses, epochs=args.epochs)
    with _output(args, "demo", in_place=True):
        result = run_demo(args.out, options, progress=not args.quiet)
    _emit(args, result, result.get("summary_text", dumps_strict(result, indent=2)))
    return result


COMMANDS = {"synth": cmd_synth, "import": cmd_import, "render": cmd_render, "slide": cmd_slide, "eval": cmd_eval,
            "triangulate": cmd_triangulate, "train": cmd_train, "predict": cmd_predict, "bench": cmd_bench,
            "demo": cmd_demo, "views": cmd_views, "preview": cmd_preview}

# -- calibration: calibrate, board, rig, undistort ------------------------------------------

def _add_calibration_parsers(sub) -> None:
    p = sub.add_parser("calibrate", help="calibrate a camera array from ChArUco board images -> rig YAML")
    p.add_argument("images", type=Path, help="IMAGES/<camera>/<frame>.png|jpg; one frame name = one instant")
    p.add_argument("--board", required=True, help="charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT, "
                   "e.g. charuco:9x6:0.05:0.0375:DICT_5X5_100")
    p.add_argument("--out", type=Path, required=True, help="rig YAML to write; pictures go to <stem>_calibration/")
    p.add_argument("--reference", help="camera whose frame is the rig's world frame (default: first by name)")
    p.add_argument("--distortion", default="k1k2p1p2", choices=("k1k2p1p2k3", "k1k2p1p2", "k1k2", "none"),
                   help="distortion coefficients to fit (default k1k2p1p2; none: pinhole)")
    p.add_argument("--min-corners", type=int, default=6, help="skip frames where a camera sees fewer corners (default 6)")
    _add_json(p)
    _add_progress(p)

    p = sub.add_parser("board", help="write the printable ChArUco board image of a SPEC")
    p.add_argument("spec", help="charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT")
    p.add_argument("--out", type=Path, required=True, help="PNG to write (records its dpi for printing at 100 %%)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--dpi", type=float, help="print resolution in pixels per inch (default 300)")
    g.add_argument("--pixels-per-square", type=int, help="side of a square in pixels (sets the dpi)")
    _add_json(p)

    p = sub.add_parser("rig", help="show, plot, undistort a rig, or convert it to and from COLMAP")
    p.add_argument("rig", nargs="?", help="rig YAML or built-in rig name (not with --from-colmap)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--from-colmap", type=Path, metavar="MODEL", help="read the cameras of a COLMAP model (needs --out)")
    g.add_argument("--to-colmap", type=Path, metavar="DIR", help="write the rig as a COLMAP model (PINHOLE cameras)")
    g.add_argument("--undistort", action="store_true", help="write the pinhole rig of the undistorted images (needs --out)")
    g.add_argument("--plot", type=Path, metavar="PNG", help="draw the rig's camera frusta")
    p.add_argument("--out", type=Path, help="rig YAML to write (--from-colmap, --undistort)")
    p.add_argument("--alpha", type=float, help="--undistort: new K from cv2.getOptimalNewCameraMatrix with this "
                   "alpha in [0,1] (0 crops to valid pixels, 1 keeps every pixel); default: keep K")
    p.add_argument("--text", action="store_true", help="--to-colmap: text model instead of binary")
    _add_json(p)

    p = sub.add_parser("undistort", help="undistort images with a rig's distortion (OpenCV remap) -> pinhole images")
    p.add_argument("images", type=Path, help="IMAGES/<camera>/<name>.png|jpg or IMAGES/<camera>.png|jpg")
    p.add_argument("--rig", required=True, help="the rig the images were taken with (with distortion)")
    p.add_argument("--out", type=Path, required=True, help="folder for the undistorted PNGs and their pinhole rig.yaml")
    p.add_argument("--alpha", type=float, help="new K from cv2.getOptimalNewCameraMatrix (default: keep K)")
    _add_json(p)
    _add_progress(p)


def cmd_calibrate(args) -> dict:
    from mvtex.calibration.board import parse_board_spec
    from mvtex.calibration.calibrate import CalibrateOptions
    from mvtex.calibration.output import calibrate_folder, pictures_folder

    options = CalibrateOptions(board=parse_board_spec(args.board), reference=args.reference,
                               min_corners=args.min_corners, distortion=args.distortion)
    calibration = calibrate_folder(args.images, args.out, options, progress=not args.quiet)
    result = calibration.summary()
    lines = [f"{name}: {c['frames']} frames ({c['skipped']} skipped), RMS {c['rms_px']:.3f} px"
             for name, c in result["per_camera"].items()]
    lines.append(f"{result['num_cameras']} cameras, {result['num_frames']} frames, RMS {result['rms_reprojection_px']:.3f}"
                 f" px; wrote {args.out} (world frame: camera {calibration.reference}), "
                 f"pictures in {pictures_folder(args.out)}")
    _emit(args, result, "\n".join(lines))
    return result


def cmd_board(args) -> dict:
    from mvtex.calibration.board import parse_board_spec, write_board_png

    result = write_board_png(parse_board_spec(args.spec), args.out, dpi=args.dpi,
                             pixels_per_square=args.pixels_per_square)
    _emit(args, result, f"wrote {args.out}: {result['width_px']}x{result['height_px']} px, print at "
          f"{result['dpi']:.0f} dpi (100 %) for {result['width_mm']:.0f} x {result['height_mm']:.0f} mm")
    return result


def cmd_rig(args) -> dict:
    from mvtex.calibration import rigs

    needs_out = args.from_colmap is not None or args.undistort
    if needs_out and args.out is None:
        raise InputError(None, "--from-colmap and --undistort need --out RIG")
    if not needs_out and args.out is not None:
        raise InputError(None, "--out goes with --from-colmap or --undistort")
    if args.alpha is not None and not args.undistort:
        raise InputError(None, "--alpha goes with --undistort")
    if args.from_colmap is not None:
        if args.rig is not None:
            raise InputError(None, "give either a RIG or --from-colmap MODEL, not both")
        rig = rigs.import_colmap(args.from_colmap, args.out)
        result = {"rig": str(args.out), **rigs.rig_summary(rig)}
        _emit(args, result, f"wrote {args.out}: {len(rig)} cameras from {args.from_colmap}")
        return result
    if args.rig is None:
        raise InputError(None, "give a RIG (a YAML or a built-in rig name)")
    rig, rig_path = _load_rig(args.rig, pinhole=False)
    if args.undistort:
        pinhole = rigs.write_pinhole_rig(rig, args.out, alpha=args.alpha)
        result = {"rig": str(args.out), **rigs.rig_summary(pinhole)}
        text = f"wrote {args.out}: pinhole rig of {len(pinhole)} cameras (" + (
            "same K" if args.alpha is None else f"K from getOptimalNewCameraMatrix, alpha {args.alpha:g}") + ")"
    elif args.to_colmap is not None:
        out = rigs.export_colmap(rig, args.to_colmap, text=args.text, source=rig_path)
        result = {"colmap": str(out), **rigs.rig_summary(rig)}
        text = f"wrote COLMAP model {out}: {len(rig)} cameras"
    elif args.plot is not None:
        rigs.plot_rig_file(rig, args.plot, title=Path(rig_path).name)
        result = {"plot": str(args.plot), **rigs.rig_summary(rig)}
        text = f"wrote {args.plot}"
    else:
        result = rigs.rig_summary(rig)
        text = "\n".join(f"{name}: {c['width']}x{c['height']}, f=({c['fx']:.1f}, {c['fy']:.1f}), c=({c['cx']:.1f}, "
                         f"{c['cy']:.1f}), centre ({', '.join(f'{v:.3f}' for v in c['center_m'])}) m"
                         + (", distorted" if name in result["distorted"] else "")
                         for name, c in result["cameras"].items())
    _emit(args, result, text)
    return result


def cmd_undistort(args) -> dict:
    from mvtex.calibration.rigs import undistort_folder

    rig, _ = _load_rig(args.rig, pinhole=False)
    result = undistort_folder(args.images, rig, args.out, alpha=args.alpha, progress=not args.quiet)
    _emit(args, result, f"wrote {result['num_images']} undistorted images and their pinhole rig to {args.out}")
    return result


COMMANDS.update({"calibrate": cmd_calibrate, "board": cmd_board, "rig": cmd_rig, "undistort": cmd_undistort})


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
