"""`mvtex train`, `mvtex predict` and `mvtex correct`: texture sliding models per camera or for every
camera, and the geometry corrector."""

from __future__ import annotations

from pathlib import Path

from mvtex.cli.common import Deprecated, UsageError, add_common, add_workers, cameras, emit, load_rig, output


def register(sub) -> None:
    p = sub.add_parser("train", help="train a texture sliding model (per camera, or one for every camera)")
    p.add_argument("dataset", type=Path, help="dataset directory")
    p.add_argument("--texcoords", type=Path, help="texcoord set with the training targets (not with --geometry)")
    p.add_argument("--geometry", action="store_true",
                   help="train the geometry corrector instead: the pose -> gt - inferred per vertex (Gaussian "
                   "processes on its principal components, --components), for `mvtex correct`")
    p.add_argument("--cameras", help="A: the model of camera A (gp by default); A,B,...: one model per camera, "
                   "OUT/<camera>, trained side by side with --workers or --scheduler; default: one network for "
                   "every camera of --texcoords, conditioned on the camera (unet)")
    p.add_argument("--camera", dest="cameras", action=Deprecated, new="--cameras A[,B...]", metavar="A[,B...]")
    p.add_argument("--rig", help="rig of the texcoord set's cameras, needed without --cameras (a rig YAML or a "
                   "built-in rig name; default TEXCOORDS/rig.yaml)")
    p.add_argument("--out", type=Path, required=True, help="model directory to write")
    p.add_argument("--arch", choices=("gp", "mlp", "unet", "paper"),
                   help="gp: Gaussian processes of the pose on the principal components of d, per camera (default "
                   "with --cameras); mlp: an ensemble of MLPs from the pose to the principal components of d, per camera; "
                   "unet: geometry images of the inferred mesh + pose, any camera (default without "
                   "--cameras); paper: the paper's pose-only decoder, per camera")
    p.add_argument("--components", type=int, help="principal components of d that gp models, or of the residual "
                   "that the geometry corrector models (default 32)")
    p.add_argument("--epochs", type=int, help="most training epochs of unet and paper (default 60)")
    p.add_argument("--resolution", type=int, help="atlas image size of unet and paper, a power of two "
                   "(default: 64 on CPU, 256 or 512 on GPU)")
    p.add_argument("--device", default=None, help="cpu, cuda, cuda:0 ... (default: cuda if available)")
    p.add_argument("--seed", type=int, default=0, help="seed of initialisation and batch order (default 0)")
    add_workers(p, "default 1; with several --cameras")
    add_common(p)
    p.set_defaults(run=cmd_train)

    p = sub.add_parser("predict", help="trained models -> texcoord set")
    p.add_argument("dataset", type=Path, help="dataset directory")
    p.add_argument("--model", type=Path, action="append", required=True,
                   help="a trained model directory (repeat: one per camera, or a camera-conditioned one)")
    p.add_argument("--out", type=Path, required=True, help="texcoord set directory to write")
    p.add_argument("--poses", default="all", help="pose SPEC: all, train, val, test, a:b or 3,5,7 (default all)")
    p.add_argument("--rig", help="predict these cameras (a camera-conditioned model serves any camera; default: "
                   "the models' own cameras)")
    add_common(p)
    p.set_defaults(run=cmd_predict)

    p = sub.add_parser("correct", help="geometry corrector -> a corrected dataset (its inferred mesh corrected)")
    p.add_argument("dataset", type=Path, help="dataset directory")
    p.add_argument("--model", type=Path, required=True, help="geometry model directory (mvtex train --geometry)")
    p.add_argument("--out", type=Path, required=True, help="dataset directory to write")
    p.add_argument("--poses", default="all", help="pose SPEC: all, train, val, test, a:b or 3,5,7 (default all)")
    p.add_argument("--shrink", type=float, default=None, metavar="K",
                   help="keep |r|2/(|r|2 + K sigma2) of each vertex's correction r, sigma its uncertainty; 0 keeps "
                   "all of it (default 0.25)")
    add_common(p)
    p.set_defaults(run=cmd_correct)


def cmd_train(args):
    from dataclasses import replace

    from mvtex.data.dataset import load_dataset

    if args.geometry:
        return cmd_train_geometry(args)
    if args.texcoords is None:
        raise UsageError("mvtex train: error: the following arguments are required: --texcoords (or --geometry)")
    from mvtex.data.texcoords import open_texcoords
    from mvtex.tsnn.train import TrainOptions, train

    changes = {k: getattr(args, k) for k in ("epochs", "resolution", "device", "components")
               if getattr(args, k) is not None}
    options = replace(TrainOptions(seed=args.seed, arch=args.arch), **changes)
    names = cameras(args.cameras)
    if args.cameras is not None and not names:
        raise UsageError(f"mvtex train: error: --cameras needs a camera name or a comma-separated list "
                         f"(got {args.cameras!r})")
    if (args.workers not in (None, 1) or args.scheduler is not None) and (names is None or len(names) < 2):
        raise UsageError("mvtex train: error: --workers above 1 and --scheduler train several cameras side by side: "
                         "give --cameras A,B,...")
    dataset = load_dataset(args.dataset)
    tc = open_texcoords(args.texcoords, dataset.num_vertices, num_poses=dataset.num_poses)
    if names is not None and len(names) > 1:
        from mvtex.tsnn.cameras import train_cameras

        with output(args, "train", in_place=True):
            result = train_cameras(dataset, tc, names, args.out, options, workers=args.workers or 1,
                                   scheduler=args.scheduler, progress=not args.quiet)
        kept = f" (kept from an earlier run with the same inputs: {', '.join(result.kept)})" if result.kept else ""
        emit(args, result, f"wrote {len(names)} models ({result.arch}) to {args.out}/<camera>: "
             f"{', '.join(names)}{kept}")
        return
    rig = None
    if names is None:
        if args.rig is None and not (args.texcoords / "rig.yaml").is_file():
            raise UsageError("mvtex train: error: one network for every camera needs their rig: give --rig "
                             "(or --cameras NAME for one camera's model)")
        rig, _ = load_rig(args.rig or str(args.texcoords / "rig.yaml"))
    with output(args, "train"):
        result = train(dataset, tc, args.out, camera=names[0] if names else None, rig=rig, options=options,
                       progress=not args.quiet)
    emit(args, result, f"wrote {args.out} ({result.arch}, {', '.join(result.cameras)})")


def cmd_predict(args):
    from mvtex.data.dataset import load_dataset
    from mvtex.tsnn.predict import predict

    dataset = load_dataset(args.dataset)
    rig = load_rig(args.rig)[0] if args.rig else None
    poses = dataset.select(args.poses)
    with output(args, "predict"):
        out = predict(dataset, args.model, args.out, poses=poses, rig=rig, progress=not args.quiet)
    emit(args, {"out": str(out), "poses": len(poses), "models": [str(m) for m in args.model]}, f"wrote {out}")


def cmd_train_geometry(args):
    from dataclasses import replace

    from mvtex.data.dataset import load_dataset
    from mvtex.tsnn.corrector import GeometryOptions, train_geometry

    unused = [flag for flag, value in (("--texcoords", args.texcoords), ("--cameras", args.cameras),
                                       ("--arch", args.arch), ("--epochs", args.epochs),
                                       ("--resolution", args.resolution), ("--rig", args.rig),
                                       ("--workers", args.workers), ("--scheduler", args.scheduler)) if value is not None]
    if unused:
        raise UsageError(f"mvtex train: error: {unused[0]} does not apply to --geometry")
    changes = {k: getattr(args, k) for k in ("components", "device") if getattr(args, k) is not None}
    options = replace(GeometryOptions(), **changes)
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
    from mvtex.tsnn.correct import CorrectOptions, correct

    options = CorrectOptions() if args.shrink is None else CorrectOptions(shrink=args.shrink)
    dataset = load_dataset(args.dataset)
    poses = dataset.select(args.poses)
    with output(args, "correct"):
        result = correct(dataset, args.model, args.out, poses=poses, options=options, progress=not args.quiet)
    rmse = "" if result.rmse_m is None else (f"; RMSE to gt {result.rmse_m['original'] * 1e3:.2f} -> "
                                             f"{result.rmse_m['corrected'] * 1e3:.2f} mm (mean over poses)")
    emit(args, result, f"wrote {result.out} ({result.poses} poses corrected, {result.out_of_sample_poses} of them "
         f"training poses of the model, out of sample; mean sigma {result.mean_sigma_m * 1e3:.2f} mm){rmse}")
