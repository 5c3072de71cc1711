"""`mvtex train`, `mvtex predict` and `mvtex correct`: texture sliding models per camera or for every
camera, and the geometry corrector."""

from __future__ import annotations

from pathlib import Path

from mvtex.cli.common import UsageError, add_common, add_workers, cameras, emit, output, rig_of
from mvtex.cli.options import add_options, options_from
from mvtex.tsnn.options import CorrectOptions, GeometryOptions, TrainOptions
from mvtex.util.options import option_fields

TRAIN_KNOBS = tuple(f.name for f, _, _ in option_fields(TrainOptions))


def register(sub) -> None:
    p = sub.add_parser("train", help="train a texture sliding model (per camera, or one for every camera)")
    p.add_argument("dataset", type=Path, help="dataset directory")
    p.add_argument("--texcoords", metavar="TC", type=Path, help="texcoord set with the training targets (required "
                   "without --geometry)")
    p.add_argument("--geometry", action="store_true",
                   help="train the geometry corrector instead: the pose -> gt - inferred per vertex (Gaussian "
                   "processes on its principal components, --components), for mvtex correct")
    p.add_argument("--cameras", metavar="A,B", help="A: the model of camera A (gp by default); A,B,...: one model per camera, "
                   "OUT/<camera>, trained side by side with --workers or --scheduler; default: one network for "
                   "every camera of --texcoords, conditioned on the camera (unet)")
    p.add_argument("--rig", help="rig of the texcoord set's cameras, needed without --cameras (a rig YAML or a "
                   "built-in rig name; default TEXCOORDS/rig.yaml); the model records its cameras from it (default: "
                   "the texcoord set's record of them)")
    p.add_argument("--out", type=Path, required=True, help="model directory to write")
    add_options(p, TrainOptions)
    add_options(p, GeometryOptions, skip=TRAIN_KNOBS)
    add_workers(p, "1; they train several --cameras side by side")
    add_common(p)
    p.set_defaults(run=cmd_train)

    p = sub.add_parser("predict", help="trained models -> texcoord set")
    p.add_argument("dataset", type=Path, help="dataset directory")
    p.add_argument("--model", metavar="MODEL", type=Path, action="append", required=True,
                   help="a trained model directory (repeat: one per camera, or a camera-conditioned one)")
    p.add_argument("--out", type=Path, required=True, help="texcoord set directory to write")
    p.add_argument("--poses", metavar="SPEC", help="pose SPEC: all, train, val, test, a:b or 3,5,7 (default: all)")
    p.add_argument("--rig", help="predict these cameras (a camera-conditioned model serves any camera; default: "
                   "the models' own cameras, recorded as OUT/rig.yaml for the commands that read the set)")
    add_common(p)
    p.set_defaults(run=cmd_predict)

    p = sub.add_parser("correct", help="geometry corrector -> a corrected dataset (its inferred mesh corrected)")
    p.add_argument("dataset", type=Path, help="dataset directory")
    p.add_argument("--model", type=Path, required=True, help="geometry model directory (mvtex train --geometry)")
    p.add_argument("--out", type=Path, required=True, help="dataset directory to write")
    p.add_argument("--poses", metavar="SPEC", help="pose SPEC: all, train, val, test, a:b or 3,5,7 (default: all)")
    add_options(p, CorrectOptions)
    add_common(p)
    p.set_defaults(run=cmd_correct)


def cmd_train(args):
    from mvtex.data.dataset import load_dataset

    if args.geometry:
        return cmd_train_geometry(args)
    if args.texcoords is None:
        raise UsageError("mvtex train: error: the following arguments are required: --texcoords (or --geometry)")
    if hasattr(args, "iterations"):
        raise UsageError("mvtex train: error: --iterations applies to --geometry only")
    from mvtex.data.texcoords import open_texcoords
    from mvtex.tsnn.cameras import train_models

    options = options_from(args, TrainOptions)
    names = cameras(args.cameras)
    dataset = load_dataset(args.dataset)
    tc = open_texcoords(args.texcoords, dataset.num_vertices, num_poses=dataset.num_poses)
    rig = rig_of(args) if args.rig is not None else None
    several = names is not None and len(names) > 1
    with output(args, "train", in_place=several):
        result = train_models(dataset, tc, args.out, names, rig=rig, options=options, workers=args.workers or 1,
                              scheduler=args.scheduler, progress=not args.quiet)
    if several:
        kept = f" (kept from an earlier run with the same inputs: {', '.join(result.kept)})" if result.kept else ""
        text = f"wrote {len(names)} models ({result.arch}) to {args.out}/<camera>: {', '.join(names)}{kept}"
    else:
        text = f"wrote {args.out} ({result.arch}, {', '.join(result.cameras)})"
    models = getattr(result, "models", None) or {args.out: result}  # several cameras, or one model
    gains = {c: m.gain for c, m in models.items() if m.gain is not None}
    if gains:
        text += ("\npredictions times the gain fitted on the validation poses (--no-gain: off): "
                 + ", ".join(f"{c} {g:.2f}" for c, g in gains.items()))
    emit(args, result, text)


def cmd_predict(args):
    from mvtex.data.dataset import load_dataset
    from mvtex.tsnn.predict import predict

    dataset = load_dataset(args.dataset)
    rig = rig_of(args) if args.rig is not None else None
    poses = dataset.select(args.poses)
    with output(args, "predict"):
        out = predict(dataset, args.model, args.out, poses=poses, rig=rig, progress=not args.quiet)
    from mvtex.data.texcoords import open_texcoords, recorded_rig

    cameras = open_texcoords(out).cameras
    rig_file = recorded_rig(out)
    where = "its cameras in rig.yaml" if rig_file is not None else "no rig recorded: give --rig to the commands after"
    emit(args, {"out": str(out), "poses": len(poses), "models": [str(m) for m in args.model], "cameras": cameras,
                "rig": None if rig_file is None else str(rig_file), "ground_truth": dataset.has_gt},
         f"wrote {out}: {len(poses)} poses x {len(cameras)} cameras ({', '.join(cameras)}), {where}")


def cmd_train_geometry(args):
    from mvtex.data.dataset import load_dataset
    from mvtex.tsnn.corrector import train_geometry

    geometry = {f.name for f, _, _ in option_fields(GeometryOptions)}
    unused = [f"--{name}" for name in ("texcoords", "cameras", "rig", "workers", "scheduler")
              if getattr(args, name, None) is not None]
    unused += [f"--{name.replace('_', '-')}" for name in TRAIN_KNOBS if name not in geometry and hasattr(args, name)]
    if unused:
        raise UsageError(f"mvtex train: error: {unused[0]} does not apply to --geometry")
    options = options_from(args, GeometryOptions)
    dataset = load_dataset(args.dataset)
    with output(args, "train"):
        result = train_geometry(dataset, args.out, options=options, progress=not args.quiet)
    v = result.validation
    emit(args, result, f"wrote {args.out} (geometry corrector, {result.components} components, "
         f"{result.num_poses['train']} training poses); validation poses: RMSE {v['rmse_m']['inferred'] * 1e3:.2f} -> "
         f"{v['rmse_m']['corrected'] * 1e3:.2f} mm, ratio median {v['ratio']['median']:.2f} / worst "
         f"{v['ratio']['worst']:.2f}, sigma calibrated x{result.sigma_scale:.2f}")


def cmd_correct(args):
    from mvtex.data.dataset import load_dataset
    from mvtex.tsnn.correct import correct

    options = options_from(args, CorrectOptions)
    dataset = load_dataset(args.dataset)
    poses = None if args.poses is None else dataset.select(args.poses)
    with output(args, "correct"):
        result = correct(dataset, args.model, args.out, poses=poses, options=options, progress=not args.quiet)
    rmse = "" if result.rmse_m is None else (f"; RMSE to gt {result.rmse_m['original'] * 1e3:.2f} -> "
                                             f"{result.rmse_m['corrected'] * 1e3:.2f} mm (mean over poses)")
    emit(args, result, f"wrote {result.out} ({result.poses} poses corrected, {result.out_of_sample_poses} of them "
         f"training poses of the model, out of sample; mean sigma {result.mean_sigma_m * 1e3:.2f} mm){rmse}")
