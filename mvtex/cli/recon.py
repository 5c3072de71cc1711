"""`mvtex triangulate`: the multi-view reconstruction of one pose -> PLY + COLMAP model."""

from __future__ import annotations

from pathlib import Path

from mvtex.cli.common import add_common, add_rig, emit, output, rig_of
from mvtex.cli.options import add_options, options_from
from mvtex.recon.options import ReconOptions


def register(sub) -> None:
    p = sub.add_parser("triangulate", help="multi-view reconstruction of one pose -> PLY + COLMAP model")
    p.add_argument("dataset", type=Path, help="dataset directory")
    add_rig(p, "the cameras of the texcoord set", from_texcoords=True)
    p.add_argument("--texcoords", metavar="TC", type=Path, required=True, help="texcoord set (from slide, predict or views)")
    p.add_argument("--pose", metavar="K", type=int, required=True, help="dataset pose index (one of the texcoord set's poses)")
    p.add_argument("--out", type=Path, required=True, help="output directory (PLY, COLMAP model, pictures, report)")
    add_options(p, ReconOptions)
    add_common(p)
    p.set_defaults(run=cmd_triangulate)


def cmd_triangulate(args):
    from mvtex.data.dataset import load_dataset
    from mvtex.data.texcoords import open_texcoords
    from mvtex.recon.pose import triangulate_pose

    options = options_from(args, ReconOptions)
    dataset = load_dataset(args.dataset)
    tc = open_texcoords(args.texcoords, dataset.num_vertices, num_poses=dataset.num_poses)
    rig = rig_of(args, names=tc.cameras)
    dataset.check_poses([args.pose])
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
        if result.original is not None:  # a corrected set (mvtex correct)
            lines.insert(1, f"corrected set: the mesh before the correction {result.original['rmse_m'] * 1e3:.2f} mm "
                         f"over all vertices, reconstructed {result.ratio_original:.2f}x better")
        files = "reconstruction.ply, colmap/, comparison.png"
    else:
        lines.append("no ground truth in the dataset: no RMSE against gt, no comparison.png")
        files = "reconstruction.ply, colmap/"
    lines.append(f"wrote {out} ({files})")
    return "\n".join(lines)
