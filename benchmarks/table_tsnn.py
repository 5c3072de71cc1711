"""TSNN on the built-in garment: the paper's Table 2 form (baseline / TSNN / TSNN +
subdivision on the test split), the error of predicted displacements on vertices assigned
by ray vs by fill (Table 4 form), and reconstruction from TSNN texcoords (stereo pair).

    python benchmarks/table_tsnn.py WORKDIR [TOTAL_POSES]

Default: a 1,200-pose dataset (960 training poses; with fewer the network barely learns,
see benchmarks/tsnn_poses.py). Trains three networks (left and right without subdivision,
left with one level) with the paper architecture (`arch="paper"`; every model is
compared in benchmarks/tsnn_learning_curve.py): about 15-20 minutes on a 2-core CPU.
"""

import json
import sys
import time
from pathlib import Path

import numpy as np

from mvtex.data.dataset import load_dataset
from mvtex.data.rig import builtin_rig_file, load_rig
from mvtex.data.texcoords import open_texcoords
from mvtex.evaluation.evaluate import evaluate
from mvtex.recon.pose import triangulate_pose
from mvtex.recon.triangulate import ReconOptions
from mvtex.sliding.dataset import slide_dataset
from mvtex.sliding.options import SlideOptions
from mvtex.synth.generate import SynthOptions, write_synth
from mvtex.tsnn.predict import predict
from mvtex.tsnn.train import TrainOptions, train_camera


def fmt(stat: dict) -> str:
    return f"{stat['mean'] * 1e3:.3f} ± {stat['std'] * 1e3:.3f}"


def picture(work: Path, ds, rig, tsnn, ts, pose: int, camera: str = "left") -> Path:
    """WORK/tsnn_heatmap.png: baseline, TSNN and TS heatmaps of one pose side by side."""
    import cv2

    cam = rig.select([camera])
    panels = {}
    for name, tc in (("tsnn", tsnn), ("ts", ts)):
        evaluate(ds, cam, tc, poses=[pose], heatmaps=work / f"heat_{name}", progress=False)
        panels[name] = cv2.imread(str(work / f"heat_{name}" / f"pose_{pose:05d}_{camera}.png"))
    w = cam.cameras[0].width
    # Each heatmap file is [baseline | gap | method | gap | colour bar], gaps 4 px wide: keep
    # baseline and TSNN from the first file, TS and the colour bar from the second.
    a, b = panels["tsnn"], panels["ts"]
    out = np.concatenate([a[:, : 2 * w + 4], a[:, w: w + 4], b[:, w + 4:]], axis=1)
    path = work / "tsnn_heatmap.png"
    cv2.imwrite(str(path), out)
    return path


def main(work: Path, total: int = 1200) -> dict:
    data = work / f"shirt{total}"
    if not (data / "dataset.json").exists():
        write_synth(data, SynthOptions(num_poses=total))
    ds = load_dataset(data)
    stereo = load_rig(builtin_rig_file("stereo"))
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
                train_camera(ds, tc, cam, model, TrainOptions(arch="paper"))
                out["train_seconds"][f"{cam}_s{subdiv}"] = round(time.perf_counter() - t, 1)
            models.append(model)
        pred = work / f"pred_s{subdiv}"
        predict(ds, models, pred, poses=test)
        pc = open_texcoords(pred, ds.num_vertices)
        r = evaluate(ds, stereo.select(["left"]), pc, progress=False).to_json()
        r_ts = evaluate(ds, stereo.select(["left"]), tc, poses=test, progress=False).to_json()
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
                reps = [triangulate_pose(ds, stereo, pc, k, None, ReconOptions(smooth=smooth), progress=False).to_json()
                        for k in test]
                recon["smooth" if smooth else "plain"] = {
                    key: float(np.mean([rep[key]["reconstructed"] for rep in reps])) for key in ("rmse_m", "rmse_triangulated_m")}
                recon["inferred"] = {key: float(np.mean([rep[key]["inferred"] for rep in reps]))
                                     for key in ("rmse_m", "rmse_triangulated_m")}
                recon["num_triangulated"] = float(np.mean([rep["num_triangulated"] for rep in reps]))
            out["reconstruction_stereo_tsnn"] = recon
            out["picture"] = str(picture(work, ds, stereo, pc, tc, test[0]))
    out["table2"] = "\n".join(rows)
    print(out["table2"])
    print(json.dumps({k: v for k, v in out.items() if k != "table2"}, indent=2))
    return out


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "tsnn-work"), int(sys.argv[2]) if len(sys.argv) > 2 else 1200)
