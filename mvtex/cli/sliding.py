"""`mvtex slide`: texture sliding over a dataset and a rig -> a texcoord set."""

from __future__ import annotations

from pathlib import Path

from mvtex.cli.common import add_common, add_rig, add_workers, cameras, emit, output, rig_of
from mvtex.cli.options import add_options, options_from
from mvtex.sliding.options import SlideOptions


def register(sub) -> None:
    p = sub.add_parser("slide", help="texture sliding over a dataset and a rig -> texcoord set")
    p.add_argument("dataset", type=Path, help="dataset directory")
    add_rig(p)
    p.add_argument("--out", type=Path, required=True,
                   help="texcoord set directory to write (resumable: rerun the same command to continue)")
    p.add_argument("--poses", metavar="SPEC", help="pose SPEC: all, train, val, test, a:b or 3,5,7 (default: all)")
    p.add_argument("--cameras", metavar="A,B", help="comma-separated camera names (default: every camera of the rig)")
    add_options(p, SlideOptions)
    add_workers(p, "one per core for long runs, else 1")
    add_common(p)
    p.set_defaults(run=cmd_slide)


def cmd_slide(args):
    from mvtex.data.dataset import load_dataset
    from mvtex.sliding.dataset import slide_complete, slide_dataset

    options = options_from(args, SlideOptions)
    dataset = load_dataset(args.dataset)
    dataset.require_gt("slide")
    rig = rig_of(args, names=cameras(args.cameras))
    poses = dataset.select(args.poses)
    with output(args, "slide"):
        complete = slide_complete(dataset, rig, args.out, poses=poses, options=options)
        out = slide_dataset(dataset, rig, args.out, poses=poses, options=options, workers=args.workers,
                            scheduler=args.scheduler, progress=False if complete else not args.quiet)
    text = (f"{out} is complete ({len(poses)} poses x {len(rig)} cameras, the same options and inputs): nothing to do"
            if complete else f"wrote {out}")
    emit(args, {"out": str(out), "poses": len(poses), "cameras": rig.names, "options": options.to_json(),
                "complete_before": complete}, text)
