"""TSNN learning curve: every method on the same test poses, at growing training sets.

    python benchmarks/tsnn_learning_curve.py WORK [--sizes 120,240,480,960] [--epochs 30] [--steps 1500]
           [--methods pca_ridge,gp,paper,unet,unet_all] [--plot docs/tsnn_learning_curve.png]
           [--dataset DATA --texcoords TS] [--threads 1] [--merge OTHER_WORK ...] [--report-only]

On the built-in garment (`mvtex synth --poses 1200`: 960 training, 120 validation, 120
test poses), targets from texture sliding with 1 subdivision on the stereo rig, scored on
camera `left` over the 120 test poses:

    inferred    the baseline: the inferred mesh with T_G
    pca_ridge   PCA of d (camera left) + ridge regression from [1, θ, θ_i θ_j] to the PCA
                coefficients; components and penalty chosen on the validation poses
    gp          `mvtex train --arch gp` (the default per camera): Gaussian processes of the pose
                on the principal components of d, camera left
    gp_reference  the same model fitted component by component (benchmarks/_gp_reference.py),
                what `gp` is measured against: `--methods gp,gp_reference` fits both at each
                size, one after the other on the same poses, and prints them side by side
                (fit times, same-chart and material ratios, and the load average of each fit)
    paper       the paper's network (pose -> FC -> transposed convolutions), camera left
    unet        geometry images of X_N + pose -> U-Net, camera left
    unet_all    one U-Net for both cameras of the rig, conditioned on the camera

Every method sees the first N training poses (N = --sizes) and the same validation poses
(early stopping / model choice). The dataset and texcoord set are made in WORK unless
--dataset and --texcoords name existing ones (`python -m mvtex synth DATA --poses 1200`,
`python -m mvtex slide DATA --rig stereo --out TS --subdiv 1`). Results are cached in WORK/results.json, so a rerun
resumes; runs split over several processes (one WORK each, sharing the dataset and the
texcoord set by links) are put together with --merge and --report-only. Prints a Markdown table (paper metric: SqrtMSE of uv over all pixels and over
same-chart pixels; material error in mm when `mvtex eval` reports it).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import time
from pathlib import Path

import numpy as np

METHODS = ("pca_ridge", "gp", "gp_reference", "paper", "unet", "unet_all")
LABELS = {"inferred": "inferred (baseline)", "pca_ridge": "PCA of d + quadratic ridge",
          "gp": "Gaussian processes on PCA of d (gp)",
          "gp_reference": "gp fitted component by component (reference)", "paper": "paper TSNN (pose only)",
          "unet": "U-Net on geometry images", "unet_all": "U-Net, both cameras, camera-conditioned"}


def quadratic_features(poses: np.ndarray, mean: np.ndarray, std: np.ndarray) -> np.ndarray:
    """[1, z, z_i z_j (i <= j)] of standardised poses z, (K, 1 + P + P(P+1)/2)."""
    z = (poses - mean) / std
    i, j = np.triu_indices(z.shape[1])
    return np.hstack([np.ones((len(z), 1)), z, z[:, i] * z[:, j]])


def fit_pca_ridge(d_train: np.ndarray, x_train: np.ndarray, d_val: np.ndarray, x_val: np.ndarray):
    """PCA of d + ridge from quadratic pose features; (components, penalty) by validation MSE.

    Args:
        d_train: (K,n,2) displacements; x_train: (K,P) poses; the same for validation.

    Returns:
        predict(x (k,P)) -> (k,n,2), and the chosen {"components", "ridge", "val_mse"}.
    """
    k, n, _ = d_train.shape
    flat = d_train.reshape(k, -1).astype(np.float64)
    mean_d = flat.mean(0)
    _, _, vt = np.linalg.svd(flat - mean_d, full_matrices=False)
    mu, sd = x_train.mean(0), np.maximum(x_train.std(0), 1e-8)
    f_train, f_val = quadratic_features(x_train, mu, sd), quadratic_features(x_val, mu, sd)
    val_flat = d_val.reshape(len(d_val), -1)
    best = None
    for comps in (2, 4, 8, 16, 32, 64):
        if comps > min(vt.shape[0], k - 1):
            continue
        basis = vt[:comps]
        coef = (flat - mean_d) @ basis.T
        for lam in (1e-2, 1e-1, 1.0, 10.0, 100.0, 1000.0):
            reg = lam * np.eye(f_train.shape[1])
            reg[0, 0] = 0.0  # the intercept is not penalised
            w = np.linalg.solve(f_train.T @ f_train + reg, f_train.T @ coef)
            err = float(np.mean((f_val @ w @ basis + mean_d - val_flat) ** 2))
            if best is None or err < best[0]:
                best = (err, comps, lam, w, basis)
    err, comps, lam, w, basis = best

    def predict(x: np.ndarray) -> np.ndarray:
        return (quadratic_features(x, mu, sd) @ w @ basis + mean_d).reshape(len(x), n, 2).astype(np.float32)

    return predict, {"components": comps, "ridge": lam, "val_mse": err}


def summary_of(result: dict) -> dict:
    """The numbers of one `evaluate` result the table shows."""
    out = {"all": result["sqrt_mse"], "same_chart": result["sqrt_mse_same_chart"], "ratio": result["ratio"],
           "ratio_same_chart": result["ratio_same_chart"]}
    material = result.get("material_rmse_m")
    if material:
        out["material_m"] = material
        out["ratio_material"] = result.get("ratio_material")
    return out


@contextlib.contextmanager
def timed_gp_fit(reference: bool, info: dict):
    """`train` fits `gp` with the library's fit or the reference; records the fit's seconds
    and the 1-minute load average before and after it in `info`."""
    from _gp_reference import fit_pose_gp as reference_fit

    from mvtex.tsnn import gp

    library = gp.fit_pose_gp
    fit = reference_fit if reference else library

    def timed(*args, **kwargs):
        info["load_before"] = round(os.getloadavg()[0], 2)
        t0 = time.perf_counter()
        model = fit(*args, **kwargs)
        info["fit_seconds"] = round(time.perf_counter() - t0, 2)
        info["load_after"] = round(os.getloadavg()[0], 2)
        return model

    gp.fit_pose_gp = timed
    try:
        yield
    finally:
        gp.fit_pose_gp = library


def run(work: Path, sizes: list[int], methods: list[str], epochs: int, steps: int, dataset: Path | None = None,
        texcoords: Path | None = None) -> dict:
    from mvtex.data.dataset import load_dataset
    from mvtex.data.rig import builtin_rig_file, load_rig
    from mvtex.data.texcoords import open_texcoords, save_texcoords
    from mvtex.evaluation.evaluate import evaluate
    from mvtex.sliding.dataset import slide_dataset
    from mvtex.sliding.options import SlideOptions
    from mvtex.synth.generate import SynthOptions, write_synth
    from mvtex.tsnn.predict import predict
    from mvtex.tsnn.train import TrainOptions, resolve_options, train

    work.mkdir(parents=True, exist_ok=True)
    data = dataset or work / "shirt1200"
    if not (data / "dataset.json").exists():
        write_synth(data, SynthOptions(num_poses=1200))
    ds = load_dataset(data)
    stereo = load_rig(builtin_rig_file("stereo"))
    left = stereo.select(["left"])
    ts = texcoords or work / "ts_stereo1"
    if not (ts / "texcoords.json").exists():
        slide_dataset(ds, stereo, ts, poses=ds.select("all"), options=SlideOptions(subdiv=1))
    tc = open_texcoords(ts, ds.num_vertices)
    train_all, val, test = ds.split["train"], ds.split["val"], ds.split["test"]
    cache = work / "results.json"
    results = json.loads(cache.read_text()) if cache.exists() else {}

    def save():
        cache.write_text(json.dumps(results, indent=2) + "\n")

    def score(pred_dir: Path) -> dict:
        return evaluate(ds, left, open_texcoords(pred_dir, ds.num_vertices), poses=test, progress=False).to_json()

    for m in sizes:
        poses = train_all[:m]
        for method in methods:
            key = f"{method}/{m}"
            if key in results:
                continue
            t0 = time.perf_counter()
            pred_dir = work / f"pred_{method}_{m}"
            info: dict = {}
            if method == "pca_ridge":
                d_train = np.stack([tc.displacement("left", p) for p in poses])
                d_val = np.stack([tc.displacement("left", p) for p in val])
                x = np.asarray(ds.poses, np.float64)
                fn, info = fit_pca_ridge(d_train, x[poses], d_val, x[val])
                d_test = fn(x[test])
                save_texcoords(pred_dir, faces=tc.faces, uv=tc.uv, parent=tc.parent, source="pca_ridge",
                               subdiv=tc.subdiv, poses=test, displacement={"left": d_test},
                               assigned={"left": np.ones(d_test.shape[:2], bool)})
            elif method in ("gp", "gp_reference"):
                model = work / f"model_{method}_{m}"
                with timed_gp_fit(method == "gp_reference", info):
                    summary = train(ds, tc, model, camera="left", options=TrainOptions(arch="gp", device="cpu"),
                                    train_poses=poses, progress=False)
                info["train_seconds"] = summary.seconds
                predict(ds, [model], pred_dir, poses=test, rig=left, progress=False)
            else:
                arch = "paper" if method == "paper" else "unet"
                # The same number of optimiser steps at every size, at least `epochs` epochs.
                n_epochs = max(epochs, -(-steps * resolve_options(TrainOptions(arch=arch)).batch_size // m))
                options = TrainOptions(arch=arch, epochs=n_epochs, device="cpu", patience=max(5, n_epochs // 4))
                model = work / f"model_{method}_{m}"
                summary = train(ds, tc, model, camera=None if method == "unet_all" else "left", rig=stereo,
                                options=options, train_poses=poses, progress=False)
                info = {"epochs_run": summary.epochs_run, "best_epoch": summary.best_epoch,
                        "train_seconds": summary.seconds}
                predict(ds, [model], pred_dir, poses=test, rig=left, progress=False)
            info["seconds"] = round(time.perf_counter() - t0, 1)
            r = score(pred_dir)
            results.setdefault("inferred", summary_of({**r, "sqrt_mse": {"texcoords": r["sqrt_mse"]["inferred"]},
                                                       "sqrt_mse_same_chart": {"texcoords": r["sqrt_mse_same_chart"]["inferred"]},
                                                       "ratio": 1.0, "ratio_same_chart": 1.0, "material_rmse_m": None}))
            results[key] = {**summary_of(r), **info}
            save()
            print(f"{key}: same-chart ratio {r['ratio_same_chart']:.2f}, all-pixel ratio {r['ratio']:.2f} "
                  f"({info['seconds']:.0f} s)", flush=True)
    return results


def table(results: dict, sizes: list[int], methods: list[str]) -> str:
    def f(stat):
        return f"{stat['mean'] * 1e3:.3f}"

    base = results["inferred"]
    material = any("material_m" in v for k, v in results.items() if k != "inferred")
    head = "| training poses | method | SqrtMSE ×10⁻³ (all pixels) | ratio | SqrtMSE ×10⁻³ (same-chart) | ratio |"
    head += " material RMSE (mm) | ratio |" if material else ""
    head += " time |"
    rows = [head, "|" + "---|" * (head.count("|") - 1),
            f"| | inferred (baseline) | {f(base['all']['texcoords'])} | 1 | {f(base['same_chart']['texcoords'])} | 1 |"
            + (" | |" if material else "") + " |"]
    for m in sizes:
        for method in methods:
            r = results.get(f"{method}/{m}")
            if r is None:
                continue
            row = (f"| {m} | {LABELS[method]} | {f(r['all']['texcoords'])} | {r['ratio']:.2f} | "
                   f"{f(r['same_chart']['texcoords'])} | {r['ratio_same_chart']:.2f} |")
            if material:
                row += (f" {r['material_m']['texcoords']['mean'] * 1e3:.2f} | {r['ratio_material']:.2f} |"
                        if "material_m" in r else " | |")
            epochs = f", {r['epochs_run']} epochs" if "epochs_run" in r else ""
            fit = f", fit {r['fit_seconds']:.1f} s" if "fit_seconds" in r else ""
            rows.append(row + f" {r['seconds']:.0f} s{epochs}{fit} |")
    return "\n".join(rows)


def gp_comparison(results: dict, sizes: list[int]) -> str:
    """`gp` beside `gp_reference` at each size both were run at: fit times (and the load
    average before and after each fit), same-chart and material ratios, and the changes."""
    head = ("| training poses | fit s, reference | fit s, gp | speed-up | same-chart ratio, reference | gp | change |"
            " material ratio, reference | gp | change | load (reference; gp) |")
    rows = [head, "|" + "---|" * (head.count("|") - 1)]
    for m in sizes:
        ref, new = results.get(f"gp_reference/{m}"), results.get(f"gp/{m}")
        if ref is None or new is None or "fit_seconds" not in ref or "fit_seconds" not in new:
            continue
        chart = (new["ratio_same_chart"] / ref["ratio_same_chart"] - 1) * 100
        material = (f"{ref['ratio_material']:.3f} | {new['ratio_material']:.3f} | "
                    f"{(new['ratio_material'] / ref['ratio_material'] - 1) * 100:+.1f} %"
                    if ref.get("ratio_material") and new.get("ratio_material") else " | | ")
        rows.append(f"| {m} | {ref['fit_seconds']:.1f} | {new['fit_seconds']:.1f} | "
                    f"{ref['fit_seconds'] / new['fit_seconds']:.1f}x | {ref['ratio_same_chart']:.3f} | "
                    f"{new['ratio_same_chart']:.3f} | {chart:+.1f} % | {material} | "
                    f"{ref['load_before']}-{ref['load_after']}; {new['load_before']}-{new['load_after']} |")
    return "\n".join(rows) if len(rows) > 2 else ""


def plot(results: dict, sizes: list[int], methods: list[str], path: Path) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.4, 4.2), dpi=110)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    for method in methods:
        xs = [m for m in sizes if f"{method}/{m}" in results]
        ax.plot(xs, [results[f"{method}/{m}"]["ratio_same_chart"] for m in xs], marker="o", label=LABELS[method])
    ax.axhline(1.0, color="gray", linestyle=":", label=LABELS["inferred"])
    ax.set_xscale("log", base=2)
    ax.set_xticks(sizes, [str(s) for s in sizes])
    ax.set_xlabel("training poses")
    ax.set_ylabel("same-chart ratio (inferred / method SqrtMSE)")
    ax.set_title("TSNN learning curve, built-in shirt, camera left, 120 test poses", fontsize=9)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, format="png")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("work", type=Path, help="working directory (dataset, texcoords, models, results.json)")
    parser.add_argument("--sizes", default="120,240,480,960", help="training set sizes (default 120,240,480,960)")
    parser.add_argument("--methods", default=",".join(METHODS), help=f"subset of {','.join(METHODS)}")
    parser.add_argument("--epochs", type=int, default=30, help="fewest epochs per network (default 30)")
    parser.add_argument("--steps", type=int, default=1500,
                        help="more epochs on small sets until a network gets this many optimiser steps (default 1500)")
    parser.add_argument("--plot", type=Path, help="write the learning-curve plot here")
    parser.add_argument("--merge", type=Path, action="append", default=[],
                        help="add the cached results of another WORK (runs split over processes)")
    parser.add_argument("--report-only", action="store_true", help="print the cached results, compute nothing")
    parser.add_argument("--dataset", type=Path, help="an existing 1,200-pose dataset (default: made in WORK)")
    parser.add_argument("--texcoords", type=Path, help="its texcoord set, stereo rig, 1 subdivision (default: made in WORK)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1: on a shared 2-core machine "
                        "one thread trains the networks several times faster)")
    args = parser.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]
    methods = [m for m in args.methods.split(",") if m]
    unknown = set(methods) - set(METHODS)
    if unknown:
        parser.error(f"unknown methods {sorted(unknown)}")
    cache = args.work / "results.json"
    if args.report_only:
        results = json.loads(cache.read_text()) if cache.exists() else {}
    else:
        import torch

        torch.set_num_threads(args.threads)
        results = run(args.work, sizes, methods, args.epochs, args.steps, args.dataset, args.texcoords)
    for other in args.merge:
        for key, value in json.loads((other / "results.json").read_text()).items():
            results.setdefault(key, value)
    if "inferred" not in results:
        parser.error(f"no results in {cache}")
    print(table(results, sizes, methods))
    comparison = gp_comparison(results, sizes)
    if comparison:
        print("\n" + comparison)
    if args.plot:
        plot(results, sizes, methods, args.plot)
        print(f"wrote {args.plot}")


if __name__ == "__main__":
    main()
