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
    p.add_argument("--use-prior", action=argparse.BooleanOptionalAction, default=True,
                   help="on a corrected set (mvtex correct), fuse each point with the corrected mesh and its sigma "
                        "(default on)")
    p.add_argument("--prior-gate", type=float, default=3.0, metavar="G",
                   help="with the prior, a point farther from it than G times their combined sigma is an outlier "
                        "(default 3)")
    p.add_argument("--no-prior-gate", dest="prior_gate", action="store_const", const=None,
                   help="keep every point whatever its distance from the prior")
    p.add_argument("--prior-fill", action=argparse.BooleanOptionalAction, default=True,
                   help="with the prior, extend the fused displacement to the vertices no camera triangulates "
                        "(default on; off: the prior stands there)")
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
                           use_uncertainty=args.use_uncertainty, use_prior=args.use_prior,
                           prior_gate=args.prior_gate, prior_fill=args.prior_fill)
    dataset = load_dataset(args.dataset)
    rig, rig_path = load_rig(rig_spec(args))
    tc = open_texcoords(args.texcoords, dataset.num_vertices, num_poses=dataset.num_poses)
    dataset.check_poses([args.pose])
    rig = rig.select(tc.cameras, rig_path)
    with output(args, "triangulate"):
        result = triangulate_pose(dataset, rig, tc, args.pose, args.out, options, progress=not args.quiet)
    emit(args, result, triangulate_summary(result, args.out))


def triangulate_summary(result, out) -> str:
    """`mvtex triangulate`'s text: the RMSE against gt first, inferred -> reconstructed, on
    the triangulated vertices and on all vertices."""
    def pair(p) -> str:
        if p.inferred is None or p.reconstructed is None:
            return "n/a"
        ratio = f" ({p.inferred / p.reconstructed:.1f}x)" if p.reconstructed else ""
        return f"{p.inferred * 1e3:.2f} mm -> {p.reconstructed * 1e3:.2f} mm{ratio}"

    reproj = result.mean_reprojection_error_px
    original = ""
    if result.original is not None:
        original = (f"\ncorrected set: the mesh before the correction {result.original['rmse_m'] * 1e3:.2f} mm over all "
                    f"vertices, reconstructed {result.ratio_original:.2f}x better")
    return (f"RMSE vs gt, inferred -> reconstructed: triangulated vertices ({result.num_triangulated} of "
            f"{result.num_vertices}) {pair(result.rmse_triangulated_m)}; all vertices {pair(result.rmse_m)}{original}\n"
            f"pose {result.pose}, mean reprojection error "
            f"{'n/a' if reproj is None else f'{reproj:.3f} px'}; wrote {out} (reconstruction.ply, colmap/, "
            "comparison.png)")
