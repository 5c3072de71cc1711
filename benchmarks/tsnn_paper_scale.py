"""Per-camera models at paper scale: learning curves of `gp` and `mlp` to thousands of poses.

    python benchmarks/tsnn_paper_scale.py WORK [--num-poses 8000] [--garment shirt] [--rig square4]
           [--cameras tl] [--sizes 250,500,1000,2000,4000,6400] [--methods gp,mlp]
           [--test-poses 200] [--workers 2] [--plot docs/tsnn_paper_scale.png] [--report-only]
           [--merge OTHER_WORK ...]

The pipeline a user runs, step by step, each step resumable (a rerun skips what is done):

    1. mvtex synth --out WORK/data --num-poses N --garment G        (skipped if WORK/data exists;
       WORK/data may be a link to an existing dataset, WORK/ts to its texcoord set)
    2. mvtex slide WORK/data --rig RIG --cameras CAMS --out WORK/ts --workers W   (an interrupted
       slide resumes; skipped once WORK/ts is finished, since slide would start a finished set over)
    3. per method and size: `mvtex.train` of each camera on the first SIZE training poses of the
       split (`train_poses`), `mvtex.predict` of the test poses, `mvtex.evaluate` (the material
       error) on the same test images; results cached in WORK/results.json after each one.

Scored on every `len(test) / TEST` -th test pose (--test-poses, default 200 of the 800 test
poses of an 8,000-pose dataset) and the given cameras; TS (the training target, what a
perfect model would predict) is scored on the same images. Prints a Markdown table: the
material error and its ratio, the same-chart ratio, and the fit time (wall clock of the
training call, this machine, whatever else runs on it, with the 1-minute load average at the
end of the row) per method and training-set size;
--plot draws ratio and fit time against the training poses.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

LABELS = {"gp": "`gp`", "mlp": "`mlp` (5 members)", "ts": "TS + 1 (the target)"}


def run(argv: list[str]) -> None:
    print("+", " ".join(argv), file=sys.stderr, flush=True)
    subprocess.run(argv, check=True)


def prepare(work: Path, args) -> None:
    mvtex = [sys.executable, "-m", "mvtex"]
    if not (work / "data" / "dataset.json").is_file():
        run([*mvtex, "synth", "--out", str(work / "data"), "--num-poses", str(args.num_poses),
             "--garment", args.garment])
    if not (work / "ts" / "texcoords.json").is_file():  # a finished set is not slid again
        run([*mvtex, "slide", str(work / "data"), "--rig", args.rig, "--cameras", args.cameras, "--out",
             str(work / "ts"), "--workers", str(args.workers)])


def score(dataset, rig: str, tc_path: Path, poses: list[int], cameras: list[str]) -> dict:
    from mvtex.evaluation.evaluate import evaluate

    r = evaluate(dataset, rig, tc_path, poses=poses, cameras=cameras, progress=True).to_json()
    m = r["material_rmse_m"]
    return {"images": r["num_images"], "ratio_material": r["ratio_material"],
            "material_mm": {"inferred": m["inferred"]["mean"] * 1e3, "texcoords": m["texcoords"]["mean"] * 1e3},
            "ratio_same_chart": r.get("ratio_same_chart"), "ratio": r["ratio"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("work", type=Path)
    ap.add_argument("--num-poses", type=int, default=8000)
    ap.add_argument("--garment", default="shirt")
    ap.add_argument("--rig", default="square4")
    ap.add_argument("--cameras", default="tl")
    ap.add_argument("--sizes", default="250,500,1000,2000,4000,6400")
    ap.add_argument("--methods", default="gp,mlp")
    ap.add_argument("--test-poses", type=int, default=200)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--plot", type=Path)
    ap.add_argument("--report-only", action="store_true")
    ap.add_argument("--merge", type=Path, nargs="*", default=[],
                    help="other WORK directories of the same dataset (runs split over processes): their results "
                    "join this one's in the report")
    args = ap.parse_args()
    work = args.work
    work.mkdir(parents=True, exist_ok=True)
    cache = work / "results.json"
    results = json.loads(cache.read_text()) if cache.is_file() else {}
    cameras = args.cameras.split(",")

    def save() -> None:
        cache.write_text(json.dumps(results, indent=1))

    if not args.report_only:
        import torch

        from mvtex.data.dataset import load_dataset
        from mvtex.data.texcoords import open_texcoords
        from mvtex.tsnn.predict import predict
        from mvtex.tsnn.train import TrainOptions, train

        torch.set_num_threads(1)
        prepare(work, args)
        dataset = load_dataset(work / "data")
        tc = open_texcoords(work / "ts", dataset.num_vertices, num_poses=dataset.num_poses)
        test = [int(p) for p in dataset.split["test"]]
        test = test[:: max(1, len(test) // args.test_poses)][: args.test_poses]
        train_all = [int(p) for p in dataset.split["train"]]
        if "ts" not in results:
            results["ts"] = {"0": score(dataset, args.rig, work / "ts", test, cameras)}
            save()
        for size in [int(s) for s in args.sizes.split(",")]:
            for method in args.methods.split(","):
                key = str(min(size, len(train_all)))
                if key in results.get(method, {}):
                    continue
                models = []
                t0 = time.perf_counter()
                for cam in cameras:
                    out = work / "models" / f"{method}_{key}" / cam
                    out.parent.mkdir(parents=True, exist_ok=True)
                    train(dataset, tc, out, camera=cam, options=TrainOptions(arch=method, device="cpu"),
                          train_poses=train_all[:size], progress=True)
                    models.append(out)
                seconds = time.perf_counter() - t0
                pred = work / "pred" / f"{method}_{key}"
                pred.parent.mkdir(parents=True, exist_ok=True)
                predict(dataset, models, pred, poses=test, progress=False)
                row = score(dataset, args.rig, pred, test, cameras)
                row["fit_seconds"] = round(seconds, 1)
                row["load"] = round(__import__("os").getloadavg()[0], 1)
                results.setdefault(method, {})[key] = row
                save()
                print(f"{method} {key}: {row}", file=sys.stderr, flush=True)

    for other in args.merge:
        for method, rows in json.loads((other / "results.json").read_text()).items():
            for size, row in rows.items():
                results.setdefault(method, {}).setdefault(size, row)
    ts = results.get("ts", {}).get("0")
    print("| training poses | method | material error (mm) | material ratio | same-chart ratio | fit time |")
    print("|---|---|---|---|---|---|")
    if ts:
        print(f"| | inferred (baseline) | {ts['material_mm']['inferred']:.2f} | 1 | 1 | |")
        print(f"| | {LABELS['ts']} | {ts['material_mm']['texcoords']:.2f} | {ts['ratio_material']:.2f} | "
              f"{ts['ratio_same_chart']:.2f} | |")
    sizes = sorted({int(k) for m, rows in results.items() if m != "ts" for k in rows})
    for size in sizes:
        for method, rows in results.items():
            r = rows.get(str(size)) if method != "ts" else None
            if r:
                print(f"| {size} | {LABELS.get(method, method)} | {r['material_mm']['texcoords']:.2f} | "
                      f"{r['ratio_material']:.2f} | {r['ratio_same_chart']:.2f} | {r['fit_seconds']:.0f} s "
                      f"(load {r.get('load', float('nan')):.0f}) |")
    if args.plot:
        plot(results, args.plot, f"{args.garment}, {args.rig} camera(s) {args.cameras}")


def plot(results: dict, path: Path, title: str) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 4), dpi=100)
    FigureCanvasAgg(fig)
    ax, bx = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    for method, rows in results.items():
        if method == "ts":
            continue
        sizes = sorted(int(k) for k in rows)
        label = LABELS.get(method, method).replace("`", "")
        ax.plot(sizes, [rows[str(s)]["ratio_material"] for s in sizes], "o-", label=label)
        bx.plot(sizes, [rows[str(s)]["fit_seconds"] for s in sizes], "o-", label=label)
    if "ts" in results:
        ax.axhline(results["ts"]["0"]["ratio_material"], color="gray", linestyle="--", label=LABELS["ts"])
    ax.axhline(4.0, color="red", linestyle=":", label="ratio 4")
    from matplotlib.ticker import NullFormatter

    ticks = sorted({int(k) for m, rows in results.items() if m != "ts" for k in rows})
    for a in (ax, bx):
        a.set_xscale("log")
        a.set_xticks(ticks, [str(t) for t in ticks])
        a.xaxis.set_minor_formatter(NullFormatter())
        a.set_xlabel("training poses")
        a.grid(True, which="both", alpha=0.3)
        a.legend(fontsize=8)
    ax.set_ylabel("material error ratio (test poses)")
    ax.set_ylim(bottom=1.0)
    bx.set_ylabel("fit time (s, one camera, shared 2-core CPU)")
    bx.set_ylim(bottom=0)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, format="png")


if __name__ == "__main__":
    main()
