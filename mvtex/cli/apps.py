"""Whole-pipeline commands: `bench` and `demo`."""

from __future__ import annotations

from pathlib import Path

from mvtex.apps.options import DemoOptions
from mvtex.cli.common import add_common, add_rig, emit, output, rig_of
from mvtex.cli.options import add_options, options_from
from mvtex.sliding.options import SlideOptions


def register(sub) -> None:
    p = sub.add_parser("bench", help="throughput: raster vs ray-cast sliding, and eval")
    p.add_argument("dataset", type=Path, help="dataset directory")
    add_rig(p)
    p.add_argument("--poses", metavar="SPEC", help="pose SPEC of the timed jobs (default: the first 20 poses)")
    add_options(p, SlideOptions, only=("subdiv",))
    p.add_argument("--workers", metavar="N", type=int, help="worker processes of the parallel measurement (default 2; 1 skips it)")
    add_common(p, overwrite=False)
    p.set_defaults(run=cmd_bench)

    p = sub.add_parser("demo", help="the whole pipeline on the built-in garment, with pictures and report.html")
    p.add_argument("--out", type=Path, default=Path("mvtex-demo"),
                   help="output directory (default mvtex-demo; rerun to resume)")
    add_options(p, DemoOptions)
    add_common(p)
    p.set_defaults(run=cmd_demo)


def cmd_bench(args):
    from mvtex.apps.bench import run_bench
    from mvtex.data.dataset import load_dataset

    dataset = load_dataset(args.dataset)
    dataset.require_gt("bench")
    rig = rig_of(args)
    poses = dataset.select(args.poses) if args.poses else None
    settings = {k: getattr(args, k) for k in ("subdiv", "workers") if getattr(args, k, None) is not None}
    result = run_bench(dataset, rig, poses=poses, progress=not args.quiet, **settings)
    emit(args, result, result.summary())


def cmd_demo(args):
    from mvtex.apps.demo import run_demo
    from mvtex.util.files import dumps_strict

    options = options_from(args, DemoOptions)
    with output(args, "demo", in_place=True):
        result = run_demo(args.out, options, progress=not args.quiet, overwrite=args.overwrite)
    emit(args, result, result.get("summary_text", dumps_strict(result, indent=2)))
