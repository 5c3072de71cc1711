"""A camera the network never trained on: one camera-conditioned U-Net trained on all
cameras of `trapezoid12` but one, scored on the one left out.

    python benchmarks/tsnn_heldout_camera.py WORK [--held-out cam05] [--train-poses 240] [--epochs 10]

Uses WORK/shirt1200 (`mvtex synth --out WORK/shirt1200 --num-poses 1200`) and texture-slides it with 1 subdivision
from `trapezoid12` on the first --train-poses training poses, 60 validation poses and the
120 test poses (WORK/ts_trap1, reused when present). Prints the held-out camera's test
scores: inferred baseline vs the network (same-chart and all-pixel SqrtMSE, their ratios).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("work", type=Path, help="working directory (shared with benchmarks/tsnn_learning_curve.py)")
    parser.add_argument("--held-out", default="cam05", help="camera left out of training (default cam05)")
    parser.add_argument("--train-poses", type=int, default=240, help="training poses (default 240)")
    parser.add_argument("--epochs", type=int, default=10, help="most epochs (default 10)")
    args = parser.parse_args()

    import torch

    from mvtex.data.dataset import load_dataset
    from mvtex.data.rig import builtin_rig_file, load_rig
    from mvtex.data.texcoords import open_texcoords
    from mvtex.evaluation.evaluate import evaluate
    from mvtex.sliding.dataset import slide_dataset
    from mvtex.sliding.options import SlideOptions
    from mvtex.synth.generate import SynthOptions, write_synth
    from mvtex.tsnn.predict import predict
    from mvtex.tsnn.train import TrainOptions, train

    torch.set_num_threads(1)  # on a shared 2-core machine one thread is several times faster
    data = args.work / "shirt1200"
    if not (data / "dataset.json").exists():
        write_synth(data, SynthOptions(num_poses=1200))
    ds = load_dataset(data)
    rig = load_rig(builtin_rig_file("trapezoid12"))
    train_poses = ds.split["train"][:args.train_poses]
    poses = sorted(train_poses + ds.split["val"][:60] + ds.split["test"])
    ts = args.work / "ts_trap1"
    if not (ts / "texcoords.json").exists():
        slide_dataset(ds, rig, ts, poses=poses, options=SlideOptions(subdiv=1))
    tc = open_texcoords(ts, ds.num_vertices)
    others = [c for c in rig.names if c != args.held_out]
    model = args.work / f"model_trap_without_{args.held_out}_{args.train_poses}"
    t0 = time.perf_counter()
    if not (model / "config.json").exists():
        train(ds, tc, model, rig=rig, cameras=others, train_poses=train_poses,
              options=TrainOptions(epochs=args.epochs, device="cpu", patience=max(3, args.epochs // 4)))
    seconds = time.perf_counter() - t0
    held = rig.select([args.held_out])
    pred = args.work / f"pred_trap_{args.held_out}_{args.train_poses}"
    predict(ds, [model], pred, poses=ds.split["test"], rig=held, progress=False)
    r = evaluate(ds, held, open_texcoords(pred, ds.num_vertices), progress=False).to_json()
    out = {"held_out": args.held_out, "trained_on": others, "train_poses": len(train_poses),
           "train_seconds": round(seconds, 1), "num_images": r["num_images"],
           "same_chart_e3": {"inferred": r["sqrt_mse_same_chart"]["inferred"]["mean"] * 1e3,
                             "network": r["sqrt_mse_same_chart"]["texcoords"]["mean"] * 1e3},
           "all_pixels_e3": {"inferred": r["sqrt_mse"]["inferred"]["mean"] * 1e3,
                             "network": r["sqrt_mse"]["texcoords"]["mean"] * 1e3},
           "ratio_same_chart": r["ratio_same_chart"], "ratio": r["ratio"]}
    if r.get("material_rmse_m"):
        out["material_rmse_m"] = r["material_rmse_m"]
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
