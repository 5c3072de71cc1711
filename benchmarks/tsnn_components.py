"""How many principal components a per-camera model needs: the ceiling of the basis, and `gp`
with more components.

    python benchmarks/tsnn_components.py WORK [--camera tl] [--rig square4] [--test-poses 200]
           [--project 32,64,128,256,512] [--size 1000] [--components 32,128]

WORK is a `tsnn_paper_scale.py` work folder (WORK/data, the dataset; WORK/ts, its TS + 1
texcoord set of the camera). Scored on the same test images as that script.

1. The ceiling: each test pose's TS + 1 displacement projected on the first C principal
   components of the training displacements (`mvtex.tsnn.pca.pose_pca`, the basis `gp` and
   `mlp` use: 2,000 evenly spaced training poses), written as a texcoord set and scored by
   `mvtex.evaluate`: the most a model of C components can reach.
2. `gp` trained on the first SIZE training poses with each component count, its test poses
   predicted and scored (fit time: wall clock of `train`, one thread).

Results are cached in WORK/components.json; prints a Markdown table.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from tsnn_paper_scale import score  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("work", type=Path)
    ap.add_argument("--camera", default="tl")
    ap.add_argument("--rig", default="square4")
    ap.add_argument("--test-poses", type=int, default=200)
    ap.add_argument("--project", default="32,64,128,256,512")
    ap.add_argument("--size", type=int, default=1000)
    ap.add_argument("--components", default="32,128")
    args = ap.parse_args()

    import torch

    from mvtex.data.dataset import load_dataset
    from mvtex.data.texcoords import open_texcoords, save_texcoords
    from mvtex.tsnn.gp import MAX_TRAIN
    from mvtex.tsnn.pca import evenly_spaced, pose_pca
    from mvtex.tsnn.predict import predict
    from mvtex.tsnn.train import TrainOptions, train

    torch.set_num_threads(1)
    work, cam = args.work, args.camera
    cache = work / "components.json"
    results = json.loads(cache.read_text()) if cache.is_file() else {"projected": {}, "gp": {}}
    dataset = load_dataset(work / "data")
    tc = open_texcoords(work / "ts", dataset.num_vertices, num_poses=dataset.num_poses)
    test = [int(p) for p in dataset.split["test"]]
    test = test[:: max(1, len(test) // args.test_poses)][: args.test_poses]
    train_all = [int(p) for p in dataset.split["train"]]

    def save() -> None:
        cache.write_text(json.dumps(results, indent=1))

    sizes = [int(c) for c in args.project.split(",")]
    if any(str(c) not in results["projected"] for c in sizes):
        basis_poses = [train_all[i] for i in evenly_spaced(len(train_all), MAX_TRAIN)]
        d = np.stack([tc.displacement(cam, p) for p in basis_poses])
        _, _, _, mean_d, basis, _ = pose_pca(dataset.poses[basis_poses].reshape(len(basis_poses), -1), d, max(sizes))
        y = np.stack([tc.displacement(cam, p) for p in test]).reshape(len(test), -1) - mean_d
        for c in sizes:
            if str(c) in results["projected"]:
                continue
            b = basis[:c]
            out = work / "projected" / str(c)
            out.parent.mkdir(parents=True, exist_ok=True)
            save_texcoords(out, faces=tc.faces, uv=tc.uv, parent=tc.parent, source="tsnn", subdiv=tc.subdiv,
                           poses=test, displacement={cam: ((y @ b.T) @ b + mean_d).reshape(len(test), -1, 2)
                                                     .astype(np.float32)},
                           assigned={cam: np.ones((len(test), len(tc.uv)), bool)}, overwrite=True)
            results["projected"][str(c)] = score(dataset, args.rig, out, test, [cam])
            save()
    for c in [int(c) for c in args.components.split(",")]:
        key = f"{args.size}_{c}"
        if key in results["gp"]:
            continue
        model = work / "components_models" / key / cam
        model.parent.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        train(dataset, tc, model, camera=cam, options=TrainOptions(arch="gp", device="cpu", components=c),
              train_poses=train_all[: args.size], progress=True)
        seconds = time.perf_counter() - t0
        pred = work / "components_pred" / key
        pred.parent.mkdir(parents=True, exist_ok=True)
        predict(dataset, [model], pred, poses=test, progress=False)
        row = score(dataset, args.rig, pred, test, [cam])
        row.update(fit_seconds=round(seconds, 1), load=round(os.getloadavg()[0], 1))
        results["gp"][key] = row
        save()

    print("| model | components | material ratio | same-chart ratio | fit time |")
    print("|---|---|---|---|---|")
    for c, r in sorted(results["projected"].items(), key=lambda kv: int(kv[0])):
        print(f"| TS + 1 projected on the basis | {c} | {r['ratio_material']:.2f} | {r['ratio_same_chart']:.2f} | |")
    for key, r in results["gp"].items():
        size, c = key.split("_")
        print(f"| `gp`, {size} training poses | {c} | {r['ratio_material']:.2f} | {r['ratio_same_chart']:.2f} | "
              f"{r['fit_seconds']:.0f} s (load {r['load']:.0f}) |")


if __name__ == "__main__":
    main()
