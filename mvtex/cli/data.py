"""Commands that make and show datasets: `synth`, `import`, `render`."""

from __future__ import annotations

from pathlib import Path

from mvtex.cli.common import add_common, add_rig, cameras, emit, output, rig_of
from mvtex.cli.options import add_options, options_from
from mvtex.synth.options import SynthOptions


def register(sub) -> None:
    p = sub.add_parser("synth", help="write a built-in garment dataset (T-shirt or skirt)")
    p.add_argument("--out", type=Path, required=True, help="dataset directory to write")
    add_options(p, SynthOptions)
    add_common(p)
    p.set_defaults(run=cmd_synth)

    p = sub.add_parser("import", help="OBJ/PLY sequences (same connectivity) -> dataset; without --gt an "
                       "inference set (new frames for trained models)")
    p.add_argument("--out", type=Path, required=True, help="dataset directory to write")
    p.add_argument("--gt", metavar="GLOB", help="glob of ground-truth meshes (sorted order = pose order); without it, "
                   "an inference set: the frames a trained model serves (predict, triangulate, views, preview, render)")
    p.add_argument("--inferred", metavar="GLOB", required=True,
                   help="glob of inferred meshes, paired with --gt in sorted order")
    p.add_argument("--rest", dest="rest_mesh", type=Path, metavar="MESH",
                   help="the garment's rest shape, an OBJ/PLY of the same connectivity (default: the first gt "
                   "mesh, or without --gt the first inferred mesh)")
    p.add_argument("--pose-vectors", metavar="FILE", type=Path,
                   help="pose vectors: .npy (K,P) or text rows (default: the frame index)")
    p.add_argument("--body", dest="body_glob", metavar="GLOB",
                   help="glob of the body's meshes (OBJ/PLY, one connectivity), paired with --gt in sorted order")
    p.add_argument("--name", help="dataset name (default: the folder name)")
    add_common(p)
    p.set_defaults(run=cmd_import)

    p = sub.add_parser("render", help="textured PNGs of gt and inferred per camera, raster dumps")
    p.add_argument("dataset", type=Path, help="dataset directory")
    add_rig(p, from_texcoords=True)
    p.add_argument("--pose", metavar="K", type=int, required=True, help="dataset pose index to render")
    p.add_argument("--out", type=Path, required=True, help="output directory (PNGs, render.json)")
    p.add_argument("--texcoords", metavar="TC", type=Path, help="texcoord set: draw the inferred mesh with its texcoords")
    p.add_argument("--raster", action="store_true", help="also write raster dumps (tri_id, bary, depth, uv)")
    p.add_argument("--cameras", metavar="A,B", help="comma-separated camera names (default: every camera of the rig)")
    add_common(p)
    p.set_defaults(run=cmd_render)


def cmd_synth(args):
    from mvtex.synth.generate import write_synth

    options = options_from(args, SynthOptions)
    with output(args, "synth"):
        result = write_synth(args.out, options, progress=not args.quiet)
    emit(args, result, f"wrote {args.out}: " + ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                                                           for k, v in result.stats.items()))


def cmd_import(args):
    from mvtex.data.dataset import load_dataset
    from mvtex.data.importer import import_sequences

    with output(args, "import"):
        path = import_sequences(args.out, args.gt, args.inferred, args.pose_vectors, name=args.name,
                                body_glob=args.body_glob, rest_mesh=args.rest_mesh, progress=not args.quiet)
    dataset = load_dataset(path)
    what = "dataset" if dataset.has_gt else "inference set (no ground truth)"
    rest = str(args.rest_mesh) if args.rest_mesh is not None else "the first gt mesh" if dataset.has_gt else \
        "the first inferred mesh"
    emit(args, {"out": str(path), "num_poses": dataset.num_poses, "num_vertices": dataset.num_vertices,
                "pose_dim": int(dataset.poses.shape[1]), "ground_truth": dataset.has_gt,
                "body": dataset.body is not None},
         f"wrote {path}: {what}, {dataset.num_poses} frames of {dataset.num_vertices} vertices, "
         f"{dataset.poses.shape[1]}-dimensional poses{', a body' if dataset.body is not None else ''}; "
         f"rest shape: {rest}")


def cmd_render(args):
    from mvtex.data.dataset import load_dataset
    from mvtex.data.texcoords import open_texcoords
    from mvtex.render.pose import render_pose

    dataset = load_dataset(args.dataset)
    rig = rig_of(args, names=cameras(args.cameras))
    tc = open_texcoords(args.texcoords, dataset.num_vertices, num_poses=dataset.num_poses) if args.texcoords else None
    dataset.check_poses([args.pose])
    with output(args, "render"):
        summary = render_pose(dataset, rig, args.pose, args.out, texcoord_set=tc, raster=args.raster,
                              progress=not args.quiet)
    emit(args, summary, f"wrote {len(summary['files'])} files to {args.out}")
