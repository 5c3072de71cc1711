"""Calibration and rig commands: `calibrate`, `board`, `rig`, `undistort`."""

from __future__ import annotations

from pathlib import Path

from mvtex.calibration.options import CalibrateOptions
from mvtex.cli.common import UsageError, add_common, command_inputs, emit, output, rig_of
from mvtex.cli.options import add_options, options_from


def register(sub) -> None:
    p = sub.add_parser("calibrate", help="calibrate a camera array from ChArUco board images -> rig YAML")
    p.add_argument("images", type=Path, help="IMAGES/<camera>/<frame>.png|jpg; one frame name = one instant")
    p.add_argument("--board", metavar="SPEC", required=True, help="charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT, "
                   "e.g. charuco:9x6:0.05:0.0375:DICT_5X5_100")
    p.add_argument("--out", type=Path, required=True, help="rig YAML to write")
    p.add_argument("--pictures", metavar="DIR", type=Path, help="also write the calibration's record (calibration.json) and "
                   "pictures (rig.png, residuals.png) into this folder")
    add_options(p, CalibrateOptions)
    add_common(p)
    p.set_defaults(run=cmd_calibrate)

    p = sub.add_parser("board", help="write the printable ChArUco board image of a SPEC")
    p.add_argument("spec", help="charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT")
    p.add_argument("--out", type=Path, required=True, help="PNG to write (records its dpi for printing at 100 %%)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--dpi", type=float, help="print resolution in pixels per inch (default 300)")
    g.add_argument("--pixels-per-square", type=int, help="side of a square in pixels (sets the dpi)")
    add_common(p)
    p.set_defaults(run=cmd_board)

    p = sub.add_parser("rig", help="show, plot or undistort a rig, or convert it to and from COLMAP")
    p.add_argument("rig", nargs="?", help="rig YAML or built-in rig name (not with --from-colmap)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--from-colmap", type=Path, metavar="MODEL", help="read the cameras of a COLMAP model (needs --out)")
    g.add_argument("--to-colmap", type=Path, metavar="DIR", help="write the rig as a COLMAP model (PINHOLE cameras)")
    g.add_argument("--undistort", action="store_true",
                   help="write the pinhole rig of the rig's undistorted images (needs --out; the images themselves: "
                        "mvtex undistort)")
    g.add_argument("--plot", type=Path, metavar="PNG", help="draw the rig's camera frusta into this PNG")
    p.add_argument("--out", type=Path, help="rig YAML to write (--from-colmap, --undistort)")
    p.add_argument("--alpha", type=float, help="--undistort: new K from cv2.getOptimalNewCameraMatrix with this "
                   "alpha in [0,1] (0 crops to valid pixels, 1 keeps every pixel); default: keep K")
    p.add_argument("--text", action="store_true", help="--to-colmap: a text model instead of binary")
    add_common(p)
    p.set_defaults(run=cmd_rig)

    p = sub.add_parser("undistort", help="undistort images with a rig's distortion (OpenCV remap) -> pinhole images")
    p.add_argument("images", type=Path, help="IMAGES/<camera>/<name>.png|jpg or IMAGES/<camera>.png|jpg")
    p.add_argument("--rig", required=True, help="the rig the images were taken with (with distortion)")
    p.add_argument("--out", type=Path, required=True,
                   help="folder for the undistorted PNGs and their pinhole rig.yaml")
    p.add_argument("--alpha", type=float, help="new K from cv2.getOptimalNewCameraMatrix (default: keep K)")
    add_common(p)
    p.set_defaults(run=cmd_undistort)


def _claim_file(args, path: Path, *inputs):
    from mvtex.util.output import claim_file

    return claim_file(path, args.command, overwrite=args.overwrite, inputs=(*inputs, *command_inputs(args)))


def cmd_calibrate(args):
    import contextlib

    from mvtex.calibration.board import parse_board_spec
    from mvtex.calibration.output import calibrate_folder

    options = options_from(args, CalibrateOptions, board=parse_board_spec(args.board))
    with _claim_file(args, args.out), \
            (output(args, "calibrate", args.pictures) if args.pictures else contextlib.nullcontext()):
        calibration = calibrate_folder(args.images, args.out, options, pictures=args.pictures,
                                       progress=not args.quiet)
    result = calibration.summary()
    lines = [f"{name}: {c['frames']} frames ({c['skipped']} skipped), RMS {c['rms_px']:.3f} px"
             for name, c in result["per_camera"].items()]
    lines.append(f"{result['num_cameras']} cameras, {result['num_frames']} frames, RMS {result['rms_reprojection_px']:.3f}"
                 f" px; wrote {args.out} (world frame: camera {calibration.reference})"
                 + (f", pictures in {args.pictures}" if args.pictures else ""))
    emit(args, result, "\n".join(lines))


def cmd_board(args):
    from mvtex.calibration.board import parse_board_spec, write_board_png

    spec = parse_board_spec(args.spec)
    with _claim_file(args, args.out):
        result = write_board_png(spec, args.out, dpi=args.dpi, pixels_per_square=args.pixels_per_square)
    emit(args, result, f"wrote {args.out}: {result['width_px']}x{result['height_px']} px, print at "
         f"{result['dpi']:.0f} dpi (100 %) for {result['width_mm']:.0f} x {result['height_mm']:.0f} mm")


def cmd_rig(args):
    from mvtex.calibration import rigs

    needs_out = args.from_colmap is not None or args.undistort
    if needs_out and args.out is None:
        raise UsageError("mvtex rig: error: --from-colmap and --undistort need --out RIG (see mvtex rig --help)")
    if not needs_out and args.out is not None:
        raise UsageError("mvtex rig: error: --out goes with --from-colmap or --undistort (see mvtex rig --help)")
    if args.alpha is not None and not args.undistort:
        raise UsageError("mvtex rig: error: --alpha goes with --undistort (see mvtex rig --help)")
    if args.from_colmap is not None:
        if args.rig is not None:
            raise UsageError("mvtex rig: error: give either a RIG or --from-colmap MODEL, not both")
        with _claim_file(args, args.out):
            rig = rigs.import_colmap(args.from_colmap, args.out)
        emit(args, {"rig": str(args.out), **rigs.rig_summary(rig)},
             f"wrote {args.out}: {len(rig)} cameras from {args.from_colmap}")
        return
    if args.rig is None:
        raise UsageError("mvtex rig: error: give a RIG (a YAML or a built-in rig name) (see mvtex rig --help)")
    rig = rig_of(args, pinhole=False)
    if args.undistort:
        with _claim_file(args, args.out):
            pinhole = rigs.write_pinhole_rig(rig, args.out, alpha=args.alpha)
        result = {"rig": str(args.out), **rigs.rig_summary(pinhole)}
        text = f"wrote {args.out}: pinhole rig of {len(pinhole)} cameras (" + (
            "same K" if args.alpha is None else f"K from getOptimalNewCameraMatrix, alpha {args.alpha:g}") + ")"
    elif args.to_colmap is not None:
        with output(args, "rig", args.to_colmap):
            out = rigs.export_colmap(rig, args.to_colmap, text=args.text)
        result = {"colmap": str(out), **rigs.rig_summary(rig)}
        text = f"wrote COLMAP model {out}: {len(rig)} cameras"
    elif args.plot is not None:
        with _claim_file(args, args.plot):
            rigs.plot_rig_file(rig, args.plot, title=Path(rig.source).name)
        result = {"plot": str(args.plot), **rigs.rig_summary(rig)}
        text = f"wrote {args.plot}"
    else:
        result = rigs.rig_summary(rig)
        text = "\n".join(f"{name}: {c['width']}x{c['height']}, f=({c['fx']:.1f}, {c['fy']:.1f}), c=({c['cx']:.1f}, "
                         f"{c['cy']:.1f}), centre ({', '.join(f'{v:.3f}' for v in c['center_m'])}) m"
                         + (", distorted" if name in result["distorted"] else "")
                         for name, c in result["cameras"].items())
    emit(args, result, text)


def cmd_undistort(args):
    from mvtex.calibration.rigs import undistort_folder

    rig = rig_of(args, pinhole=False)
    with output(args, "undistort"):
        result = undistort_folder(args.images, rig, args.out, alpha=args.alpha, progress=not args.quiet)
    emit(args, result, f"wrote {result['num_images']} undistorted images and their pinhole rig to {args.out}")
