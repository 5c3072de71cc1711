"""`mvtex triangulate`: the multi-view reconstruction of one pose -> PLY + COLMAP model."""

from __future__ import annotations

import argparse
from pathlib import Path

from mvtex.cli.common import add_common, add_rig, emit, library_names, load_rig, output, rig_spec


def register(sub) -> None:
    p = sub.add_parser("triangulate", help="multi-view reconstruction of one pose -> PLY + COLMAP model")
    p.add_argument("dataset", type=Path, help="dataset directory")
    add_rig(p, "the cameras of the texcoord set", from_texcoords=True)
    p.add_argument("--texcoords", type=Path, required=True, help="texcoord set (from slide, predict or views)")
    p.add_argument("--pose", type=int, required=True, help="dataset pose index (one of the texcoord set's poses)")
    p.add_argument("--out", type=Path, required=True, help="output directory (PLY, COLMAP model, pictures, report)")
    p.add_argument("--smooth", action=argparse.BooleanOptionalAction, default=False,
                   help="smooth the reconstructed displacement (for noisy inputs such as TSNN texcoords; default off)")
    p.add_argument("--max-reprojection-px", type=float, default=2.0,
                   help="drop observations and reject points above this reprojection error (default 2 px)")
    library_names(p.add_argument("--max-surface-distance", type=float, default=0.05,
                                 help="reject points farther than this from the inferred surface (default 0.05 m)"),
                  "max_surface_distance_m")
    p.add_argument("--max-stretch", type=float, default=1.75, metavar="R",
                   help="drop observations located in a triangle with an edge whose texcoords stretch more than R "
                        "times its material length (T_N across a fold edge; default 1.75)")
    p.add_argument("--no-max-stretch", dest="max_stretch", action="store_const", const=None,
                   help="keep observations whatever their triangle's stretch")
    p.add_argument("--consensus-px", type=float, default=0.5,
                   help="the cameras' vote: an observation agrees with a point within this (default 0.5 px)")
    p.add_argument("--consensus-scale", type=float, default=None, metavar="S",
                   help="grow the vote's threshold to S times the pose's median reprojection error (default: 4 "
                        "for predicted texcoords, 0 for slid ones)")
    p.add_argument("--shrink", type=float, default=None, metavar="K",
                   help="trust in each point: keep tau2/(tau2 + K sigma2) of its displacement, sigma its standard "
                        "deviation, tau2 the pose's mean squared displacement; 0 takes every point (default: 0.2 "
                        "for predicted texcoords, 0 for slid ones)")
    p.add_argument("--use-uncertainty", action=argparse.BooleanOptionalAction, default=True,
                   help="weigh observations and trust points by the texcoord set's uncertainty.npy where it has "
                        "one (default on; off: by the cameras' disagreement)")
    p.add_argument("--fill-shape", choices=("rest", "inferred"), default="rest",
                   help="the shape the displacement of untriangulated vertices is extended on (default rest)")
    p.add_argument("--engine", choices=("mvtex", "pycolmap"), default="mvtex",
                   help="who triangulates the tracks: mvtex (vectorised DLT + Gauss-Newton, faster) or pycolmap "
                        "(COLMAP multi-view triangulation + points-only bundle adjustment); the same points")
    add_common(p)
    p.set_defaults(run=cmd_triangulate)


def cmd_triangulate(args):
    from mvtex.data.dataset import load_dataset
    from mvtex.data.texcoords import open_texcoords
    from mvtex.recon.pose import triangulate_pose
    from mvtex.recon.triangulate import ReconOptions

    options = ReconOptions(smooth=args.smooth, max_reprojection_px=args.max_reprojection_px,
                           max_surface_distance_m=args.max_surface_distance, max_stretch=args.max_stretch,
                           consensus_px=args.consensus_px, consensus_scale=args.consensus_scale,
                           fill_shape=args.fill_shape, engine=args.engine, shrink=args.shrink,
                           use_uncertainty=args.use_uncertainty)
    dataset = load_dataset(args.dataset)
    rig, rig_path = load_rig(rig_spec(args))
    tc = open_texcoords(args.texcoords, dataset.num_vertices, num_poses=dataset.num_poses)
    dataset.check_poses([args.pose])
    rig = rig.select(tc.cameras, rig_path)
    with output(args, "triangulate"):
        result = triangulate_pose(dataset, rig, tc, args.pose, args.out, options, progress=not args.quiet)
    emit(args, result, triangulate_summary(result, args.out))


def triangulate_summary(result, out) -> str:
    """`mvtex triangulate`'s text: where the dataset has gt, the RMSE against it first
    (inferred -> reconstructed); then what it says without gt, which leads for an inference
    set: the triangulated share, the reprojection error, the mean trust in the points and
    how far the reconstruction moved the inferred mesh."""
    def pair(p) -> str:
        if p.inferred is None or p.reconstructed is None:
            return "n/a"
        ratio = f" ({p.inferred / p.reconstructed:.1f}x)" if p.reconstructed else ""
        return f"{p.inferred * 1e3:.2f} mm -> {p.reconstructed * 1e3:.2f} mm{ratio}"

    reproj = result.mean_reprojection_error_px
    trust = "n/a" if result.mean_trust is None else f"{result.mean_trust:.2f}"
    moved = result.displacement_m
    lines = [f"pose {result.pose}: triangulated {result.num_triangulated} of {result.num_vertices} vertices "
             f"({100 * result.triangulated_share:.1f} %), mean reprojection error "
             f"{'n/a' if reproj is None else f'{reproj:.3f} px'}, mean trust {trust}; moved from the inferred mesh "
             f"{moved['mean'] * 1e3:.2f} mm on average, {moved['max'] * 1e3:.2f} mm at most"]
    if result.rmse_m is not None:
        lines.insert(0, f"RMSE vs gt, inferred -> reconstructed: triangulated vertices ({result.num_triangulated} of "
                     f"{result.num_vertices}) {pair(result.rmse_triangulated_m)}; all vertices {pair(result.rmse_m)}")
        files = "reconstruction.ply, colmap/, comparison.png"
    else:
        lines.append("no ground truth in the dataset: no RMSE against gt, no comparison.png")
        files = "reconstruction.ply, colmap/"
    lines.append(f"wrote {out} ({files})")
    return "\n".join(lines)
