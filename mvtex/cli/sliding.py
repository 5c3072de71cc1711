"""`mvtex slide`: texture sliding over a dataset and a rig -> a texcoord set."""

from __future__ import annotations

import argparse
from pathlib import Path

from mvtex.cli.common import add_common, add_rig, add_workers, cameras, emit, load_rig, output


class BreakRatio(argparse.Action):
    """`--break-ratio R` / `--no-break-ratio`; the old `--break-ratio off` still works (warned)."""

    def __call__(self, parser, namespace, values, option_string=None):
        if option_string == "--no-break-ratio":
            namespace.break_ratio = None
        elif str(values).strip().lower() == "off":
            namespace._deprecated = getattr(namespace, "_deprecated", []) + [("--break-ratio off", "--no-break-ratio")]
            namespace.break_ratio = None
        else:
            try:
                namespace.break_ratio = float(values)
            except ValueError:
                parser.error(f"argument --break-ratio: invalid number: {values!r}")
        namespace.break_ratio_set = True


class OnOff(argparse.Action):
    """`--x` / `--no-x`; the old `--x on|off` still works (warned)."""

    def __call__(self, parser, namespace, values, option_string=None):
        flag = self.option_strings[0]
        if option_string.startswith("--no-"):
            value = False
        elif values is None:
            value = True
        elif str(values).lower() in ("on", "off"):
            namespace._deprecated = getattr(namespace, "_deprecated", []) + [(f"{flag} {values}",
                                                                              f"{flag} or --no-{flag[2:]}")]
            value = str(values).lower() == "on"
        else:
            parser.error(f"argument {flag}: takes no value (got {values!r}); use {flag} or --no-{flag[2:]}")
        setattr(namespace, self.dest, value)


def register(sub) -> None:
    p = sub.add_parser("slide", help="texture sliding over a dataset and a rig -> texcoord set")
    p.add_argument("dataset", type=Path, help="dataset directory")
    add_rig(p)
    p.add_argument("--out", type=Path, required=True,
                   help="texcoord set directory to write (resumable: rerun the same command to continue)")
    p.add_argument("--poses", default="all", help="pose SPEC: all, train, val, test, a:b or 3,5,7 (default all)")
    p.add_argument("--subdiv", type=int, default=1, choices=(0, 1, 2),
                   help="midpoint subdivision levels of the inferred mesh (default 1)")
    p.add_argument("--fill", default="harmonic", choices=("harmonic", "fmm"),
                   help="fill of unassigned vertices: harmonic (cotangent Laplace) or fmm (default harmonic)")
    p.add_argument("--max-displacement", type=float, help="unassign vertices with |d| above this (uv units; default: no limit)")
    p.add_argument("--break-ratio", "--no-break-ratio", dest="break_ratio", action=BreakRatio, nargs="?",
                   metavar="R", help="break edges whose |dT_N| exceeds R x their |dT_G| (R > 1); --no-break-ratio: "
                   "the paper's plain method (the default)")
    p.add_argument("--radius", type=int, help="candidate window half-size in pixels, 1 = 3x3 (default 1)")
    p.add_argument("--depth-tolerance", type=float, help="relative tolerance of the vertex depth test (default 1e-3)")
    p.add_argument("--cross-chart", "--no-cross-chart", dest="cross_chart", action=OnOff, nargs="?",
                   help="keep hits on another UV chart than the vertex's own (default --no-cross-chart)")
    p.add_argument("--cameras", help="comma-separated camera names (default: every camera of the rig)")
    add_workers(p, "default: one per core for long runs, else 1")
    add_common(p)
    p.set_defaults(run=cmd_slide, break_ratio_set=False)


def slide_options(args):
    """The `SlideOptions` of the flags (flags not given keep the library's defaults)."""
    from mvtex.sliding.options import SlideOptions

    changes = {k: getattr(args, k) for k in ("radius", "depth_tolerance", "cross_chart", "max_displacement")
               if getattr(args, k) is not None}
    if args.break_ratio_set:
        changes["break_ratio"] = args.break_ratio
    return SlideOptions(subdiv=args.subdiv, fill=args.fill, **changes)


def cmd_slide(args):
    from mvtex.data.dataset import load_dataset
    from mvtex.sliding.dataset import slide_complete, slide_dataset

    options = slide_options(args)
    dataset = load_dataset(args.dataset)
    dataset.require_gt("slide")
    rig, rig_path = load_rig(args.rig)
    rig = rig.select(cameras(args.cameras), rig_path)
    poses = dataset.select(args.poses)
    with output(args, "slide"):
        complete = slide_complete(dataset, rig, args.out, poses=poses, options=options, cameras=rig.names)
        out = slide_dataset(dataset, rig_path, args.out, poses=poses, options=options, cameras=rig.names,
                            workers=args.workers, scheduler=args.scheduler, progress=False if complete else not args.quiet)
    text = (f"{out} is complete ({len(poses)} poses x {len(rig)} cameras, the same options and inputs): nothing to do"
            if complete else f"wrote {out}")
    emit(args, {"out": str(out), "poses": len(poses), "cameras": rig.names, "options": options.to_json(),
                "complete_before": complete}, text)
