"""Reconstruction accuracy per garment and rig with the default options: the table of
docs/reconstruction.md.

    python benchmarks/table_recon.py WORK [--garments shirt,skirt] [--dataset DIR ...]
        [--rigs stereo,square4,trapezoid12] [--poses test] [--num-poses 300] [--subdiv 1]
        [--source ts,tsnn] [--tsnn-poses 200] [--tsnn-test-poses N] [--tsnn-rigs square4]
        [--slide KEY=VALUE ...]
        [--recon KEY=VALUE ...] [--workers N] [--json FILE]

TS: the built-in garment (`mvtex synth --garment G --poses NUM_POSES`, or a dataset given
with --dataset) is slid with `slide`'s defaults (override with --slide break_ratio=4) for
each rig, and each selected pose is triangulated with `triangulate`'s defaults (override
with --recon). TSNN: a dataset of TSNN_POSES poses is slid on every pose, one `gp` model
per camera of each TSNN rig is trained on its train split (minutes per camera), the test
poses (or N of them, evenly spaced, with --tsnn-test-poses) are predicted and triangulated:
every point taken (without and with `smooth`), trusted by the cameras' agreement (the set's
uncertainty ignored), and with the defaults (trusted by the models' predictive uncertainty);
TS on the same test poses is reported next to it. Everything is written under WORK and reused by a rerun.

Per (garment, rig, source): triangulated share, RMSE over the triangulated and over all
vertices (inferred -> reconstructed, mean over poses), the ratio inferred / reconstructed
RMSE on the triangulated vertices and over all vertices (median and worst pose), the
mean reprojection error,
and the located observations left out, summed over poses, by reason (plus rejected
points by reason). Prints markdown tables; --json writes every number.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import fields
from pathlib import Path

import numpy as np

from mvtex.data.dataset import load_dataset
from mvtex.data.rig import builtin_rig_file, load_rig
from mvtex.data.texcoords import open_texcoords
from mvtex.recon.consensus import OBSERVATION_REASONS
from mvtex.recon.options import ReconOptions
from mvtex.recon.pose import triangulate_pose
from mvtex.render.context import GLContext
from mvtex.sliding.dataset import slide_dataset
from mvtex.sliding.options import SlideOptions
from mvtex.synth.generate import SynthOptions, write_synth

RIGS = ("stereo", "square4", "trapezoid12")
POINT_REASONS = ("fewer_than_2_views", "disagreement", "cheirality", "reprojection", "surface_distance")


def _typed(cls, pairs: list[str]) -> dict:
    """KEY=VALUE strings -> keyword arguments of the dataclass cls (VALUE as JSON, else a
    string; none or off: None)."""
    known = {f.name for f in fields(cls)}
    out = {}
    for pair in pairs:
        key, _, value = pair.partition("=")
        if key not in known:
            raise SystemExit(f"{cls.__name__} has no field {key!r}")
        try:
            out[key] = None if value.lower() in ("none", "off") else json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def _dataset(work: Path, garment: str, num_poses: int, given: dict[str, Path]):
    if garment in given:
        return load_dataset(given[garment])
    path = work / f"{garment}{num_poses}"
    if not (path / "dataset.json").exists():
        write_synth(path, SynthOptions(num_poses=num_poses, garment=garment))
    return load_dataset(path)


def summarise(dataset, rig, texcoords, poses: list[int], options: ReconOptions, ctx) -> dict:
    """Triangulate the poses and aggregate their reports (the table's columns)."""
    reports = [triangulate_pose(dataset, rig, texcoords, k, None, options, progress=False, ctx=ctx).to_json()
               for k in poses]
    ratio = np.array([r["rmse_triangulated_m"]["inferred"] / r["rmse_triangulated_m"]["reconstructed"]
                      for r in reports])
    ratio_all = np.array([r["rmse_m"]["inferred"] / r["rmse_m"]["reconstructed"] for r in reports])
    mean = lambda f: float(np.mean([f(r) for r in reports]))  # noqa: E731
    return {
        "poses": list(map(int, poses)),
        "cameras": reports[0]["cameras"],
        "triangulated_share": mean(lambda r: r["num_triangulated"] / r["num_vertices"]),
        "rmse_triangulated_mm": {"inferred": 1e3 * mean(lambda r: r["rmse_triangulated_m"]["inferred"]),
                                 "reconstructed": 1e3 * mean(lambda r: r["rmse_triangulated_m"]["reconstructed"])},
        "rmse_all_mm": {"inferred": 1e3 * mean(lambda r: r["rmse_m"]["inferred"]),
                        "reconstructed": 1e3 * mean(lambda r: r["rmse_m"]["reconstructed"])},
        "ratio_triangulated": {"median": float(np.median(ratio)), "worst": float(ratio.min()),
                               "worst_pose": int(poses[int(np.argmin(ratio))]), "per_pose": ratio.tolist()},
        "ratio_all": {"median": float(np.median(ratio_all)), "worst": float(ratio_all.min()),
                      "worst_pose": int(poses[int(np.argmin(ratio_all))]), "per_pose": ratio_all.tolist()},
        "reprojection_px": mean(lambda r: r["mean_reprojection_error_px"]),
        "rejected_observations": {k: int(sum(r["rejected_observations"][k] for r in reports))
                                  for k in OBSERVATION_REASONS},
        "used_observations": int(sum(r["stats"]["used_observations"] for r in reports)),
        "rejected_points": {k: int(sum(r["rejected"][k] for r in reports)) for k in POINT_REASONS},
        "consensus_threshold_px": mean(lambda r: r["stats"]["consensus_threshold_px"]),
    }


def run_ts(work: Path, dataset, garment: str, rig_name: str, poses: list[int], slide: SlideOptions,
           options: ReconOptions, workers: int, ctx) -> dict:
    rig = load_rig(builtin_rig_file(rig_name))
    tag = "".join(f"_{k}{v}" for k, v in sorted(vars(slide).items()) if getattr(SlideOptions(), k) != v)
    path = work / f"{garment}_ts_{rig_name}{tag or '_defaults'}"
    slide_dataset(dataset, rig, path, poses=poses, options=slide, workers=workers, progress=False, ctx=ctx)
    return summarise(dataset, rig, open_texcoords(path, dataset.num_vertices), poses, options, ctx)


def run_tsnn(work: Path, garment: str, rig_name: str, num_poses: int, slide: SlideOptions, options: ReconOptions,
             workers: int, given: dict[str, Path], ctx, test_poses: int | None = None) -> dict:
    """TS and TSNN (plain and smoothed) on the test split of a num_poses dataset (every
    len(test) / test_poses -th test pose when test_poses is given)."""
    from dataclasses import replace

    from mvtex.tsnn.cameras import train_cameras
    from mvtex.tsnn.predict import predict
    from mvtex.tsnn.train import TrainOptions

    dataset = _dataset(work, garment, num_poses, given)
    rig = load_rig(builtin_rig_file(rig_name))
    base = work / f"{garment}{num_poses}_tsnn_{rig_name}"
    ts = base / "ts_all"
    slide_dataset(dataset, rig, ts, poses=dataset.select("all"), options=slide, workers=workers, progress=False,
                  ctx=ctx)
    tc = open_texcoords(ts, dataset.num_vertices)
    train_cameras(dataset, tc, list(rig.names), base / "models", TrainOptions(arch="gp"), workers=workers,
                  progress=False)
    test = [int(k) for k in dataset.split["test"]]
    if test_poses:
        test = test[::max(1, len(test) // test_poses)][:test_poses]
    pred = base / ("tsnn_test" if len(test) == len(dataset.split["test"]) else f"tsnn_test{len(test)}")
    if not (pred / "texcoords.json").exists():
        predict(dataset, [base / "models" / c for c in rig.names], pred, poses=test, progress=False)
    pc = open_texcoords(pred, dataset.num_vertices)
    untrusted = replace(options, shrink=0.0, use_uncertainty=False)
    return {"ts": summarise(dataset, rig, tc, test, options, ctx),
            "tsnn_plain": summarise(dataset, rig, pc, test, untrusted, ctx),
            "tsnn_smooth": summarise(dataset, rig, pc, test, replace(untrusted, smooth=True), ctx),
            "tsnn_consistency": summarise(dataset, rig, pc, test, replace(options, use_uncertainty=False), ctx),
            "tsnn": summarise(dataset, rig, pc, test, options, ctx)}


def row(garment: str, rig: str, source: str, s: dict) -> str:
    r, t, a = s["ratio_triangulated"], s["rmse_triangulated_mm"], s["rmse_all_mm"]
    q = s["ratio_all"]
    return (f"| {garment} | {rig} | {source} | {100 * s['triangulated_share']:.1f} % | {t['inferred']:.2f} → "
            f"{t['reconstructed']:.3f} | {a['inferred']:.2f} → {a['reconstructed']:.2f} | {r['median']:.1f}× / "
            f"{r['worst']:.1f}× | {q['median']:.2f}× / {q['worst']:.2f}× | {s['reprojection_px']:.3f} |")


def rejection_row(garment: str, rig: str, source: str, s: dict) -> str:
    obs = s["rejected_observations"]
    return (f"| {garment} | {rig} | {source} | {s['used_observations']} | "
            + " | ".join(str(obs[k]) for k in OBSERVATION_REASONS) + " | "
            + ", ".join(f"{k} {v}" for k, v in s["rejected_points"].items() if v) + " |")


def markdown(results: list[tuple[str, str, str, dict]]) -> str:
    head = ["| garment | rig | texcoords | triangulated | RMSE triangulated (mm) | RMSE all (mm) "
            "| ratio triangulated, median / worst pose | ratio all, median / worst pose | reprojection (px) |",
            "|---|---|---|---|---|---|---|---|---|"]
    rej = ["| garment | rig | texcoords | used | " + " | ".join(OBSERVATION_REASONS) + " | points rejected |",
           "|---|---|---|---|" + "---|" * len(OBSERVATION_REASONS) + "---|"]
    for g, r, source, s in results:
        head.append(row(g, r, source, s))
        rej.append(rejection_row(g, r, source, s))
    return "\n".join(head) + "\n\nObservations left out, summed over the poses:\n\n" + "\n".join(rej)


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("work", type=Path)
    p.add_argument("--garments", default="shirt,skirt", help="built-in garments (or names given with --dataset)")
    p.add_argument("--dataset", action="append", default=[], metavar="NAME=DIR",
                   help="use this dataset for garment NAME (e.g. a T-shirt on a mannequin)")
    p.add_argument("--rigs", default=",".join(RIGS))
    p.add_argument("--poses", default="test", help="pose SPEC of the TS rows (default the test split)")
    p.add_argument("--num-poses", type=int, default=300, help="poses of the built-in TS dataset")
    p.add_argument("--subdiv", type=int, default=1)
    p.add_argument("--source", default="ts", help="ts, tsnn or ts,tsnn")
    p.add_argument("--tsnn-poses", type=int, default=200, help="poses of the TSNN dataset (80 %% train)")
    p.add_argument("--tsnn-test-poses", type=int, help="score only this many test poses, evenly spaced (default all)")
    p.add_argument("--tsnn-rigs", default="square4", help="rigs of the TSNN rows (one gp model per camera)")
    p.add_argument("--slide", action="append", default=[], metavar="KEY=VALUE", help="a SlideOptions field")
    p.add_argument("--recon", action="append", default=[], metavar="KEY=VALUE", help="a ReconOptions field")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--json", type=Path, help="write every number here")
    args = p.parse_args(argv)
    given = {}
    for item in args.dataset:
        name, _, path = item.partition("=")
        given[name] = Path(path)
    slide = SlideOptions(**{"subdiv": args.subdiv, **_typed(SlideOptions, args.slide)})
    options = ReconOptions(**_typed(ReconOptions, args.recon))
    sources = args.source.split(",")
    args.work.mkdir(parents=True, exist_ok=True)
    results: list[tuple[str, str, str, dict]] = []
    with GLContext() as ctx:
        for garment in args.garments.split(","):
            if "ts" in sources:
                dataset = _dataset(args.work, garment, args.num_poses, given)
                poses = dataset.select(args.poses)
                for rig_name in args.rigs.split(","):
                    results.append((garment, rig_name, "TS", run_ts(args.work, dataset, garment, rig_name, poses,
                                                                     slide, options, args.workers, ctx)))
                    print(row(*results[-1]), file=sys.stderr, flush=True)
            if "tsnn" in sources:
                for rig_name in args.tsnn_rigs.split(","):
                    out = run_tsnn(args.work, garment, rig_name, args.tsnn_poses, slide, options, args.workers, given,
                                   ctx, args.tsnn_test_poses)
                    for source, label in (("ts", f"TS ({args.tsnn_poses}-pose set)"),
                                          ("tsnn_plain", "TSNN, every point taken"),
                                          ("tsnn_smooth", "TSNN, every point taken, smooth"),
                                          ("tsnn_consistency", "TSNN, trust from the cameras' agreement"),
                                          ("tsnn", "TSNN, trust from the uncertainty (defaults)")):
                        results.append((garment, rig_name, label, out[source]))
                        print(row(*results[-1]), file=sys.stderr, flush=True)
    table = markdown(results)
    print(f"slide {vars(slide)}\ntriangulate {vars(options)}\n\n{table}")
    summary = {"slide": vars(slide), "options": vars(options), "table": table,
               "rows": [{"garment": g, "rig": r, "texcoords": s, **v} for g, r, s, v in results]}
    if args.json:
        args.json.write_text(json.dumps(summary, indent=1))
    return summary


if __name__ == "__main__":
    main()
