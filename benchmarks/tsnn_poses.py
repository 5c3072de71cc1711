"""How the TSNN's test accuracy grows with the number of training poses, on the built-in
garment (camera `left` of the stereo rig, no subdivision), with the paper architecture;
benchmarks/tsnn_learning_curve.py compares every method at these sizes.

    python benchmarks/tsnn_poses.py WORKDIR [TOTAL_POSES] [TRAIN_SIZES]

Defaults: a 1,200-pose dataset (80/10/10 split: 960 training, 120 validation, 120 test
poses) and networks trained on its first 120, 240, 480 and 960 training poses, all scored
on the same 120 test poses. Prints a Markdown table; about 15 minutes on a 2-core CPU.
"""

import json
import sys
import time
from pathlib import Path

from mvtex.data.dataset import load_dataset
from mvtex.data.rig import builtin_rig_file, load_rig
from mvtex.data.texcoords import open_texcoords
from mvtex.evaluation.evaluate import evaluate
from mvtex.sliding.dataset import slide_dataset
from mvtex.sliding.options import SlideOptions
from mvtex.synth.generate import SynthOptions, write_synth
from mvtex.tsnn.predict import predict
from mvtex.tsnn.train import TrainOptions, train_camera


def fmt(stat: dict) -> str:
    return f"{stat['mean'] * 1e3:.3f} ± {stat['std'] * 1e3:.3f}"


def main(work: Path, total: int = 1200, sizes: tuple[int, ...] = (120, 240, 480, 960)) -> str:
    data = work / f"shirt{total}"
    if not (data / "dataset.json").exists():
        write_synth(data, SynthOptions(num_poses=total))
    ds = load_dataset(data)
    left = load_rig(builtin_rig_file("stereo")).select(["left"])
    train, val, test = ds.split["train"], ds.split["val"], ds.split["test"]
    rows = ["| training poses | TSNN SqrtMSE ×10⁻³ (all) | ratio | TSNN SqrtMSE ×10⁻³ (same-chart) | ratio | training time |",
            "|---|---|---|---|---|---|"]
    base = None
    for m in sizes:
        if m > len(train):
            continue
        # The training split of a texcoord set is the dataset's, restricted to its poses.
        ts = work / f"ts_left_{m}"
        slide_dataset(ds, left, ts, poses=sorted([*train[:m], *val, *test]), options=SlideOptions(subdiv=0))
        model = work / f"net_left_{m}"
        summary_path = work / f"net_left_{m}.json"
        if not summary_path.exists():
            t = time.perf_counter()
            summary = train_camera(ds, open_texcoords(ts, ds.num_vertices), "left", model,
                                   TrainOptions(arch="paper")).to_json()
            summary["wall_seconds"] = round(time.perf_counter() - t, 1)
            summary_path.write_text(json.dumps(summary, indent=2))
        summary = json.loads(summary_path.read_text())
        pred = work / f"pred_left_{m}"
        predict(ds, [model], pred, poses=test, progress=False)
        r = evaluate(ds, left, open_texcoords(pred, ds.num_vertices), progress=False).to_json()
        if base is None:
            base = r
            rows.insert(2, f"| (baseline: inferred) | {fmt(r['sqrt_mse']['inferred'])} | 1 | "
                           f"{fmt(r['sqrt_mse_same_chart']['inferred'])} | 1 | |")
        rows.append(f"| {m} | {fmt(r['sqrt_mse']['texcoords'])} | {r['ratio']:.2f} | "
                    f"{fmt(r['sqrt_mse_same_chart']['texcoords'])} | {r['ratio_same_chart']:.2f} | "
                    f"{summary['wall_seconds']:.0f} s ({summary['epochs_run']} epochs) |")
        print(rows[-1], flush=True)
    table = "\n".join(rows)
    print(table)
    return table


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "tsnn-poses-work"),
         int(sys.argv[2]) if len(sys.argv) > 2 else 1200,
         tuple(int(s) for s in sys.argv[3].split(",")) if len(sys.argv) > 3 else (120, 240, 480, 960))
