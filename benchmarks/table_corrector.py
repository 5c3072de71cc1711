"""The learned path beside its plain baseline: the table of docs/tsnn.md and the README.

    python benchmarks/table_corrector.py WORK [--garments shirt,skirt] [--num-poses 300]
        [--split test] [--test-poses N] [--rigs square4,trapezoid12] [--no-stereo]
        [--recon KEY=VALUE ...] [--workers 2] [--json FILE]
    python benchmarks/table_corrector.py WORK --data DATA [--no-plain] ...   (an existing dataset)
    python benchmarks/table_corrector.py --merge A.json B.json ...    (one table of their rows)

For each built-in garment, a dataset of NUM_POSES poses (`mvtex synth --garment G
--num-poses N`, 80 % of them training poses) at WORK/data/<garment><N>, and everything
made from it under WORK/work/<garment><N> (every step is kept and reused by a rerun; with
--data an existing dataset instead, its work under WORK/work/<its folder name>):

    ts_RIG, gp_RIG/<camera>, gp{val,test}_RIG    the plain per-camera path: `slide` (below),
                                                 `train` (gp, every camera), `predict`
    geometry, corrected                          `train --geometry`, `correct` (every pose)
    cts_RIG, cgp_RIG/<camera>, cgp{val,test}_RIG the same per-camera path on the corrected set

(A rerun reuses the predictions it finds: delete [c]gp{val,test}_RIG to score new models.)
`slide` runs on the training and validation poses and the poses scored (a later run that
scores other test poses needs [c]ts_RIG deleted first). --no-plain skips the
plain per-camera path (its slides and models, the `gp` column): at paper scale it is the
per-camera models' own benchmark (docs/tsnn.md), and sliding the set once more is an hour.

The five columns, on the poses of SPLIT (N evenly spaced ones with --test-poses):
inferred; the corrector alone (the corrected mesh); per-camera `gp` alone (on the original
mesh); the corrector + `gp` (models trained on the corrected set, fused with its prior in
`triangulate`); texture sliding from gt on the corrected mesh (the ceiling). Measures:
`stereo` material error (`eval`, mean over the images of both cameras; for the corrector
alone the corrected mesh with T_G), and for each rig of --rigs the all-vertex RMSE ratio
original inferred / method per pose (`triangulate`'s defaults, --recon overrides), median
and worst. Every ratio is to the original inferred mesh.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
from table_recon import _typed

from mvtex.data.dataset import load_dataset
from mvtex.data.mesh import rms_distance
from mvtex.data.rig import builtin_rig_file, load_rig
from mvtex.data.texcoords import open_texcoords
from mvtex.evaluation.evaluate import evaluate
from mvtex.recon.options import ReconOptions
from mvtex.recon.pose import triangulate_pose
from mvtex.render.context import GLContext
from mvtex.sliding.dataset import slide_dataset
from mvtex.sliding.options import SlideOptions
from mvtex.synth.generate import SynthOptions, write_synth
from mvtex.tsnn.cameras import train_cameras
from mvtex.tsnn.correct import correct
from mvtex.tsnn.corrector import train_geometry
from mvtex.tsnn.predict import predict
from mvtex.tsnn.train import TrainOptions

COLUMNS = ("inferred", "corrector", "gp", "corrector + gp, fused", "TS from gt on the corrected mesh")


def scored_poses(dataset, split: str, count: int | None) -> list[int]:
    """The poses of `split`, or `count` evenly spaced ones of them."""
    poses = [int(k) for k in dataset.split[split]]
    if count and count < len(poses):
        poses = [poses[int(i)] for i in np.unique(np.linspace(0, len(poses) - 1, count).round())]
    return poses


def prepare(dataset, base: Path, rigs: list[str], scored: list[int], workers: int, plain: bool = True) -> None:
    """Every model and texcoord set of one dataset (each step skipped when it is there)."""
    base.mkdir(parents=True, exist_ok=True)
    if not (base / "geometry" / "config.json").exists():
        train_geometry(dataset, base / "geometry", progress=False)
    if not (base / "corrected" / "dataset.json").exists():
        correct(dataset, base / "geometry", base / "corrected", progress=False)
    corrected = load_dataset(base / "corrected")
    slid = sorted(set(dataset.split["train"]) | set(dataset.split["val"]) | set(scored))
    for prefix, ds in (("", dataset), ("c", corrected)) if plain else (("c", corrected),):
        for rig_name in rigs:
            rig = load_rig(builtin_rig_file(rig_name))
            ts = base / f"{prefix}ts_{rig_name}"
            if not (ts / "texcoords.json").exists():
                slide_dataset(ds, rig, ts, poses=slid, options=SlideOptions(), workers=workers, progress=False)
            models = base / f"{prefix}gp_{rig_name}"
            outs = {split: base / f"{prefix}gp{split}_{rig_name}" for split in ("val", "test")}
            if all((out / "texcoords.json").exists() for out in outs.values()):
                continue  # kept predictions: delete them to score new models
            # One process: models trained on worker processes are not recorded in the folder's
            # manifest, and a rerun would refuse the folder.
            train_cameras(ds, open_texcoords(ts, ds.num_vertices), list(rig.names), models, TrainOptions(arch="gp"),
                          progress=False)
            for split, out in outs.items():
                if not (out / "texcoords.json").exists():
                    predict(ds, [models / c for c in rig.names], out, poses=ds.split[split], progress=False)


def _ratios(values: list[float]) -> dict:
    r = np.asarray(values)
    return {"median": float(np.median(r)), "worst": float(r.min()), "per_pose": r.tolist()}


def reconstruction(dataset, corrected, base: Path, rig_name: str, poses: list[int], options: ReconOptions,
                   ctx, fused_only: bool = False, plain: bool = True) -> dict:
    """All-vertex RMSE ratios (original inferred / method) per pose, four methods (the fused
    one alone with `fused_only`: a study of its options; no `gp` column without `plain`)."""
    rig = load_rig(builtin_rig_file(rig_name))
    split = "val" if set(poses) <= set(dataset.split["val"]) else "test"
    out = {"corrector": [], "gp": [], "corrector + gp, fused": [], "TS from gt on the corrected mesh": []}
    gp = open_texcoords(base / f"gp{split}_{rig_name}", dataset.num_vertices) if plain else None
    cgp = open_texcoords(base / f"cgp{split}_{rig_name}", dataset.num_vertices)
    cts = open_texcoords(base / f"cts_{rig_name}", dataset.num_vertices)
    extra: dict[str, list] = {"mean_trust": [], "prior_outliers": [], "triangulated_share": []}
    for k in poses:
        gt = dataset.gt[k]
        original = rms_distance(dataset.inferred[k], gt)
        out["corrector"].append(original / rms_distance(corrected.inferred[k], gt))
        if not fused_only and plain:
            r = triangulate_pose(dataset, rig, gp, k, None, options, progress=False, ctx=ctx)
            out["gp"].append(r.rmse_m.inferred / r.rmse_m.reconstructed)
        if not fused_only:
            r = triangulate_pose(corrected, rig, cts, k, None, options, progress=False, ctx=ctx)
            out["TS from gt on the corrected mesh"].append(r.ratio_original)
        r = triangulate_pose(corrected, rig, cgp, k, None, options, progress=False, ctx=ctx)
        out["corrector + gp, fused"].append(r.ratio_original)
        extra["mean_trust"].append(r.stats.get("mean_trust", 1.0))
        extra["prior_outliers"].append(r.stats.get("prior_outliers", 0))
        extra["triangulated_share"].append(r.num_triangulated / r.num_vertices)
    summary = {name: _ratios(v) for name, v in out.items() if v}
    summary["fused_stats"] = {k: float(np.mean(v)) for k, v in extra.items()}
    return summary


def rendering(dataset, corrected, base: Path, poses: list[int], ctx) -> dict:
    """`stereo` material error (mm, mean over images) of the five columns."""
    rig = load_rig(builtin_rig_file("stereo"))
    split = "val" if set(poses) <= set(dataset.split["val"]) else "test"
    plain = evaluate(dataset, rig, base / f"gp{split}_stereo", poses=poses, progress=False, ctx=ctx)
    fused = evaluate(corrected, rig, base / f"cgp{split}_stereo", poses=poses, progress=False, ctx=ctx)
    ceiling = evaluate(corrected, rig, base / "cts_stereo", poses=poses, progress=False, ctx=ctx)
    mm = {"inferred": plain.material_rmse_m.inferred.mean,
          "corrector": fused.material_rmse_m.inferred.mean,
          "gp": plain.material_rmse_m.texcoords.mean,
          "corrector + gp, fused": fused.material_rmse_m.texcoords.mean,
          "TS from gt on the corrected mesh": ceiling.material_rmse_m.texcoords.mean,
          "original, on the corrected set's images": fused.original_inferred["material_rmse_m"].mean}
    return {k: 1e3 * v for k, v in mm.items()} | {"num_images": plain.num_images}


def cell(value: dict | float | None, inferred_mm: float | None = None) -> str:
    if value is None:
        return "-"
    if isinstance(value, dict):
        return f"{value['median']:.2f} / {value['worst']:.2f}"
    return f"{value:.2f} mm ({inferred_mm / value:.2f}×)"


def markdown(rows: list[dict]) -> str:
    lines = ["| garment (training poses) | measure | " + " | ".join(COLUMNS) + " |",
             "|---|---|" + "---|" * len(COLUMNS)]
    for row in rows:
        label = f"{row['garment']} ({row['train_poses']})"
        if "stereo" in row:
            s = row["stereo"]
            lines.append(f"| {label} | `stereo` material error, {s['num_images']} images | {s['inferred']:.2f} mm | "
                         + " | ".join(cell(s[c], s["inferred"]) for c in COLUMNS[1:]) + " |")
        for rig_name, r in row["rigs"].items():
            lines.append(f"| {label} | `{rig_name}` all-vertex RMSE ratio, median / worst ({len(row['poses'])} poses) "
                         "| 1 | " + " | ".join(cell(r.get(c)) for c in COLUMNS[1:]) + " |")
    return "\n".join(lines)


def merge(files: list[Path]) -> str:
    """The table of the rows of several --json outputs, in the order given."""
    return markdown([row for f in files for row in json.loads(Path(f).read_text())["rows"]])


def main(argv: list[str] | None = None) -> dict:
    if argv is None:
        argv = sys.argv[1:]
    if argv and argv[0] == "--merge":  # python benchmarks/table_corrector.py --merge A.json B.json ...
        table = merge([Path(f) for f in argv[1:]])
        print(table)
        return {"table": table}
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("work", type=Path)
    p.add_argument("--garments", default="shirt,skirt")
    p.add_argument("--data", type=Path, help="score this existing dataset instead of the built-in garments")
    p.add_argument("--plain", action=argparse.BooleanOptionalAction, default=True,
                   help="the plain per-camera path on the original mesh (the `gp` column)")
    p.add_argument("--num-poses", type=int, default=300, help="poses of each dataset (80 %% training poses)")
    p.add_argument("--split", default="test", choices=("val", "test"), help="the poses scored (val to choose defaults)")
    p.add_argument("--test-poses", type=int, help="score only this many poses of the split, evenly spaced")
    p.add_argument("--rigs", default="square4,trapezoid12", help="rigs of the reconstruction rows")
    p.add_argument("--stereo", action=argparse.BooleanOptionalAction, default=True, help="the material error row")
    p.add_argument("--prepare-only", action="store_true", help="make the models and sets, score nothing")
    p.add_argument("--fused-only", action="store_true", help="score the fused column alone (a study of --recon)")
    p.add_argument("--recon", action="append", default=[], metavar="KEY=VALUE", help="a ReconOptions field")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--json", type=Path, help="write every number here")
    args = p.parse_args(argv)
    if args.stereo and not args.plain:
        p.error("--no-plain needs --no-stereo (the stereo row's inferred column comes from the plain path)")
    options = ReconOptions(**_typed(ReconOptions, args.recon))
    rigs = [r for r in args.rigs.split(",") if r]
    rows = []
    with GLContext() as ctx:
        for garment in [None] if args.data else args.garments.split(","):
            if args.data:
                data, base = args.data, args.work / "work" / args.data.resolve().name
            else:
                data = args.work / "data" / f"{garment}{args.num_poses}"
                base = args.work / "work" / f"{garment}{args.num_poses}"
                if not (data / "dataset.json").exists():
                    write_synth(data, SynthOptions(num_poses=args.num_poses, garment=garment))
            dataset = load_dataset(data)
            garment = garment or dataset.name
            poses = scored_poses(dataset, args.split, args.test_poses)
            prepare(dataset, base, rigs + (["stereo"] if args.stereo else []), poses, args.workers, args.plain)
            if args.prepare_only:
                continue
            corrected = load_dataset(base / "corrected")
            row = {"garment": garment, "num_poses": dataset.num_poses, "train_poses": len(dataset.split["train"]),
                   "split": args.split, "poses": poses, "rigs": {}}
            if args.stereo:
                row["stereo"] = rendering(dataset, corrected, base, poses, ctx)
            for rig_name in rigs:
                row["rigs"][rig_name] = reconstruction(dataset, corrected, base, rig_name, poses, options, ctx,
                                                       args.fused_only, args.plain)
            rows.append(row)
            print(markdown(rows[-1:]), file=sys.stderr, flush=True)
    table = markdown(rows)
    print(f"triangulate {vars(replace(options))}\n\n{table}")
    summary = {"options": vars(options), "table": table, "rows": rows}
    if args.json:
        args.json.write_text(json.dumps(summary, indent=1))
    return summary


if __name__ == "__main__":
    main()
