"""TSNN on the built-in garment: the paper's Table 2 form (baseline / TSNN / TSNN +
subdivision on the test split), the error of predicted displacements on vertices assigned
by ray vs by fill (Table 4 form), and reconstruction from TSNN texcoords (stereo pair).

    python examples/table_tsnn.py WORKDIR

Trains three networks (left and right without subdivision, left with one level) with the
default settings: about 5-10 minutes on a 2-core CPU.
"""

import json
import sys
import time
from pathlib import Path

import numpy as np

from mvtex.camera import builtin_rig_path, load_rig
from mvtex.dataset import load_dataset
from mvtex.metrics import evaluate
from mvtex.recon import ReconOptions, triangulate_pose
from mvtex.sliding import SlideOptions, slide_dataset
from mvtex.synth import SynthOptions, write_synth
from mvtex.texcoords import open_texcoords
from mvtex.tsnn.predict import predict
from mvtex.tsnn.train import TrainOptions, train_camera


def fmt(stat: dict) -> str:
    return f"{stat['mean'] * 1e3:.3f} ± {stat['std'] * 1e3:.3f}"


def main(work: Path) -> dict:
    if not (work / "shirt" / "dataset.json").exists():
        write_synth(work / "shirt", SynthOptions())
    ds = load_dataset(work / "shirt")
    stereo = load_rig(builtin_rig_path("stereo"))
    test = ds.split["test"]
    out: dict = {"train_seconds": {}}
    rows = ["| method (test split, camera left) | SqrtMSE ×10⁻³ (all pixels) | ratio | SqrtMSE ×10⁻³ (same-chart) | ratio |",
            "|---|---|---|---|---|"]
    for subdiv, cameras in ((0, ("left", "right")), (1, ("left",))):
        ts = work / f"tsall_s{subdiv}"
        slide_dataset(ds, stereo, ts, poses=ds.select("all"), options=SlideOptions(subdiv=subdiv))
        tc = open_texcoords(ts, ds.num_vertices)
        models = []
        for cam in cameras:
            model = work / f"net_{cam}_s{subdiv}"
            if not (model / "config.json").exists():
                t = time.perf_counter()
                train_camera(ds, tc, cam, model, TrainOptions())
                out["train_seconds"][f"{cam}_s{subdiv}"] = round(time.perf_counter() - t, 1)
            models.append(model)
        pred = work / f"pred_s{subdiv}"
        predict(ds, models, pred, poses=test)
        pc = open_texcoords(pred, ds.num_vertices)
        r = evaluate(ds, stereo.select(["left"]), pc, progress=False)
        r_ts = evaluate(ds, stereo.select(["left"]), tc, poses=test, progress=False)
        if subdiv == 0:
            rows.append(f"| inferred (baseline) | {fmt(r['sqrt_mse']['inferred'])} | 1 | {fmt(r['sqrt_mse_same_chart']['inferred'])} | 1 |")
        rows.append(f"| TSNN{' + subdivision' if subdiv else ''} | {fmt(r['sqrt_mse']['texcoords'])} | {r['ratio']:.2f} "
                    f"| {fmt(r['sqrt_mse_same_chart']['texcoords'])} | {r['ratio_same_chart']:.2f} |")
        rows.append(f"| TS{' + subdivision' if subdiv else ''} (its training target) | {fmt(r_ts['sqrt_mse']['texcoords'])} "
                    f"| {r_ts['ratio']:.2f} | {fmt(r_ts['sqrt_mse_same_chart']['texcoords'])} | {r_ts['ratio_same_chart']:.2f} |")
        # Table 4 form: error of the predicted d against the TS target, by how TS assigned it.
        ray, fill, zero_ray, zero_fill = [], [], [], []
        for k in test:
            d_ts, a = tc.displacement("left", k), tc.assigned("left", k)
            err = np.linalg.norm(pc.displacement("left", k) - d_ts, axis=1)
            ray.append(err[a]), fill.append(err[~a])
            zero_ray.append(np.linalg.norm(d_ts[a], axis=1)), zero_fill.append(np.linalg.norm(d_ts[~a], axis=1))
        rms = lambda v: float(np.sqrt(np.mean(np.concatenate(v) ** 2)))  # noqa: E731
        out[f"vertex_rmse_s{subdiv}"] = {"ray": rms(ray), "fill": rms(fill), "zero_ray": rms(zero_ray),
                                         "zero_fill": rms(zero_fill)}
        if subdiv == 0:
            recon = {}
            for smooth in (False, True):
                reps = [triangulate_pose(ds, stereo, pc, k, None, ReconOptions(smooth=smooth), progress=False) for k in test]
                recon["smooth" if smooth else "plain"] = {
                    key: float(np.mean([rep[key]["reconstructed"] for rep in reps])) for key in ("rmse_m", "rmse_triangulated_m")}
                recon["inferred"] = {key: float(np.mean([rep[key]["inferred"] for rep in reps]))
                                     for key in ("rmse_m", "rmse_triangulated_m")}
                recon["num_triangulated"] = float(np.mean([rep["num_triangulated"] for rep in reps]))
            out["reconstruction_stereo_tsnn"] = recon
    out["table2"] = "\n".join(rows)
    print(out["table2"])
    print(json.dumps({k: v for k, v in out.items() if k != "table2"}, indent=2))
    return out


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "tsnn-work"))
