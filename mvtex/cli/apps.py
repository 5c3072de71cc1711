"""Whole-pipeline commands: `bench` and `demo`."""

from __future__ import annotations

from pathlib import Path

from mvtex.cli.common import Deprecated, add_common, add_rig, emit, load_rig, output


def register(sub) -> None:
    p = sub.add_parser("bench", help="throughput: raster vs ray-cast sliding, and eval")
    p.add_argument("dataset", type=Path, help="dataset directory")
    add_rig(p)
    p.add_argument("--poses", default="0:20", help="pose SPEC of the timed jobs (default 0:20)")
    p.add_argument("--subdiv", type=int, default=1, choices=(0, 1, 2),
                   help="midpoint subdivisions of the inferred mesh (default 1)")
    p.add_argument("--workers", type=int, default=2,
                   help="worker processes of the parallel measurement (default 2; 1 skips it)")
    add_common(p, overwrite=False)
    p.set_defaults(run=cmd_bench)

    p = sub.add_parser("demo", help="the whole pipeline on the built-in garment, with pictures and report.html")
    p.add_argument("--out", type=Path, default=Path("mvtex-demo"),
                   help="output directory (default mvtex-demo; rerun to resume)")
    p.add_argument("--num-poses", type=int, default=120, help="poses to synthesize (default 120)")
    p.add_argument("--poses", dest="num_poses", type=int, action=Deprecated, new="--num-poses N", metavar="N")
    p.add_argument("--epochs", dest="ignored_epochs", type=int, action=Deprecated, new=None, metavar="E",
                   help="deprecated; has no effect (the demo's per-camera model, gp, has no epochs)")
    add_common(p)
    p.set_defaults(run=cmd_demo)


def cmd_bench(args):
    from mvtex.apps.bench import run_bench
    from mvtex.data.dataset import load_dataset

    dataset = load_dataset(args.dataset)
    dataset.require_gt("bench")
    _, rig_path = load_rig(args.rig)
    poses = dataset.select(args.poses)
    result = run_bench(dataset, rig_path, poses=poses, subdiv=args.subdiv, workers=args.workers,
                       progress=not args.quiet)
    emit(args, result, result.summary())


def cmd_demo(args):
    from mvtex.apps.demo import DemoOptions, run_demo
    from mvtex.util.files import dumps_strict

    options = DemoOptions(num_poses=args.num_poses)
    with output(args, "demo", in_place=True):
        result = run_demo(args.out, options, progress=not args.quiet, overwrite=args.overwrite)
    emit(args, result, result.get("summary_text", dumps_strict(result, indent=2)))
