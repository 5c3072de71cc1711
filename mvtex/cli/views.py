"""`mvtex views`, `mvtex preview` and `mvtex export`: novel views between array cameras, stereo
previews, and a pose as a glTF scene with a viewer."""

from __future__ import annotations

from pathlib import Path

from mvtex.cli.common import add_common, add_rig, add_workers, cameras, command_inputs, emit, output, rig_of
from mvtex.cli.options import add_options, options_from
from mvtex.views.options import ExportOptions, PreviewOptions, ViewOptions


def register(sub) -> None:
    p = sub.add_parser("views", help="texcoords of novel views between array cameras -> texcoord set + rig.yaml")
    p.add_argument("dataset", type=Path, help="dataset directory")
    add_rig(p, "the array's cameras", from_texcoords=True)
    p.add_argument("--texcoords", metavar="TC", type=Path, required=True, help="the array's texcoord set (from slide or predict)")
    p.add_argument("--out", type=Path, required=True, help="texcoord set to write (with OUT/rig.yaml, the views)")
    p.add_argument("--poses", metavar="SPEC", help="pose SPEC (default: the texcoord set's poses)")
    add_options(p, ViewOptions)
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--weights", metavar="WEIGHTS", help='one view: "A=0.3,B=0.7" (weights >= 0 summing to 1)')
    g.add_argument("--between", metavar="A,B", help="A,B: --steps views evenly from A to B, both ends included")
    g.add_argument("--grid", metavar="A,B,C,D", help="A,B,C,D: --steps x --steps views bilinear over a 2x2 array (row-major from A)")
    p.add_argument("--steps", metavar="N", type=int, help="number of views along --between, per side of --grid (required with "
                   "them)")
    p.add_argument("--name", help='name of the --weights view (default: "view")')
    p.add_argument("--plot", type=Path, help="also write a PNG of SqrtMSE along the views (needs gt): the baseline, "
                   "this method and TS computed directly at each view")
    add_workers(p, "1")
    add_common(p)
    p.set_defaults(run=cmd_views)

    p = sub.add_parser("preview", help="stereo AR preview: left/right eye renders, anaglyph, SSIM/PSNR vs gt")
    p.add_argument("dataset", type=Path, help="dataset directory")
    add_rig(p, "the array's cameras", from_texcoords=True)
    p.add_argument("--texcoords", metavar="TC", type=Path, required=True, help="the array's texcoord set")
    p.add_argument("--pose", metavar="K", type=int, required=True, help="dataset pose index (one of the texcoord set's poses)")
    p.add_argument("--out", type=Path, required=True,
                   help="output folder: stereo.png, anaglyph.png, comparison.png, preview.json")
    p.add_argument("--weights", metavar="WEIGHTS", help='viewpoint "A=0.5,B=0.5" (default: equal weights over the rig\'s cameras)')
    add_options(p, PreviewOptions)
    add_common(p)
    p.set_defaults(run=cmd_preview)

    p = sub.add_parser("export", help="a pose as a glTF scene (every camera's texcoords, the cameras, the body) "
                                      "+ viewer.html that blends them as you turn the view")
    p.add_argument("dataset", type=Path, help="dataset directory (no ground truth needed)")
    p.add_argument("--texcoords", metavar="TC", type=Path, required=True, help="the cameras' texcoord set (slide, predict or views)")
    add_rig(p, "the set's cameras", from_texcoords=True)
    p.add_argument("--pose", metavar="K", type=int, required=True, help="dataset pose index (one of the texcoord set's poses)")
    p.add_argument("--out", type=Path, required=True, help="output folder: scene.glb, viewer.html, export.json")
    add_options(p, ExportOptions)
    add_common(p)
    p.set_defaults(run=cmd_export)


def cmd_views(args):
    from dataclasses import replace

    from mvtex.data.dataset import load_dataset
    from mvtex.data.texcoords import open_texcoords
    from mvtex.util.errors import OptionError
    from mvtex.views.cameras import plan_views
    from mvtex.views.novel import novel_views

    weights, names = plan_views(weights=args.weights, between=cameras(args.between), grid=cameras(args.grid),
                                steps=args.steps, name=args.name)
    if args.plot is not None and args.weights is not None:
        raise OptionError("plot", "needs the views of between or grid")
    options = options_from(args, ViewOptions)
    dataset = load_dataset(args.dataset)
    rig = rig_of(args)
    tc = open_texcoords(args.texcoords, dataset.num_vertices, num_poses=dataset.num_poses)
    poses = dataset.select(args.poses) if args.poses else None
    import contextlib

    from mvtex.util.output import claim_file

    # The plot measures the views against gt: an inference set has none, so it is skipped (said once).
    plot_path = args.plot if dataset.has_gt else None
    plot = claim_file(plot_path, "views", overwrite=args.overwrite, inputs=[*command_inputs(args), rig.source]) \
        if plot_path else contextlib.nullcontext()
    with output(args, "views"), plot:
        result = novel_views(dataset, rig, tc, args.out, weights, names, poses=poses, options=options,
                             progress=not args.quiet, workers=args.workers or 1,
                             scheduler=args.scheduler)
        if plot_path is not None:
            from mvtex.views.measure import path_plot

            result = replace(result, measured=path_plot(dataset, rig, tc, weights, names, plot_path, poses=poses,
                                                        progress=not args.quiet))
    skipped = f"; {dataset.path} has no ground truth: no --plot (it compares with gt)" \
        if args.plot is not None and plot_path is None else ""
    emit(args, result, f"wrote {len(names)} view(s) x {len(result.poses)} pose(s) ({options.method}) to {args.out}"
         + skipped)


def cmd_preview(args):
    from mvtex.data.dataset import load_dataset
    from mvtex.data.texcoords import open_texcoords
    from mvtex.views.cameras import parse_weights
    from mvtex.views.preview import stereo_preview

    options = options_from(args, PreviewOptions)
    weights = parse_weights(args.weights) if args.weights else None
    dataset = load_dataset(args.dataset)
    rig = rig_of(args)
    tc = open_texcoords(args.texcoords, dataset.num_vertices, num_poses=dataset.num_poses)
    with output(args, "preview"):
        result = stereo_preview(dataset, rig, tc, args.pose, args.out, weights=weights, options=options,
                                progress=not args.quiet, overwrite=args.overwrite)
    left, right = result.eyes["left"].ssim, result.eyes["right"].ssim
    if left is None:  # an inference set: nothing to score against
        text = (f"pose {result.pose}: {dataset.path} has no ground truth: no SSIM/PSNR against gt (the comparison "
                f"shows inferred and texcoords only); wrote {args.out}")
    else:
        text = (f"pose {result.pose}: SSIM inferred -> texcoords: left {left[0]:.3f} -> {left[1]:.3f}, "
                f"right {right[0]:.3f} -> {right[1]:.3f}; wrote {args.out}")
    emit(args, result, text)


def cmd_export(args):
    from mvtex.data.dataset import load_dataset
    from mvtex.data.texcoords import open_texcoords
    from mvtex.views.scene import export_scene

    options = options_from(args, ExportOptions)
    dataset = load_dataset(args.dataset)
    rig = rig_of(args)
    tc = open_texcoords(args.texcoords, dataset.num_vertices, num_poses=dataset.num_poses)
    with output(args, "export"):
        result = export_scene(dataset, tc, args.pose, args.out, rig=rig, options=options, overwrite=args.overwrite)
    emit(args, result, f"pose {result.pose}: {result.num_vertices} vertices, texcoords of "
         f"{', '.join(result.cameras)}; wrote {', '.join(result.files)} to {args.out}")
