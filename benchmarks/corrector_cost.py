"""The geometry corrector's fit beside one camera's `gp` fit, side by side on one dataset.

    python benchmarks/corrector_cost.py DATA --texcoords TC --camera NAME WORK [--repeats 2]

Alternates `train --geometry` (`mvtex.train_geometry`) and `train --cameras NAME`
(`mvtex.train`, `gp`) REPEATS times each on the same dataset, writing the models under
WORK, and reports each fit's wall-clock seconds and the CPU seconds of this process (all
threads) with the load average before it: on a shared machine the CPU seconds are the
comparable figure. Both fits use every training pose of DATA (TC: a texcoord set of
every training pose, from `slide`).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

from mvtex.data.dataset import load_dataset
from mvtex.data.texcoords import open_texcoords
from mvtex.tsnn.corrector import train_geometry
from mvtex.tsnn.train import TrainOptions, train


def timed(fit) -> dict:
    load = os.getloadavg()[0]
    wall, cpu = time.perf_counter(), time.process_time()
    fit()
    return {"wall_s": round(time.perf_counter() - wall, 2), "cpu_s": round(time.process_time() - cpu, 2),
            "load_before": round(load, 2)}


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("data", type=Path)
    p.add_argument("work", type=Path)
    p.add_argument("--texcoords", type=Path, required=True)
    p.add_argument("--camera", required=True)
    p.add_argument("--repeats", type=int, default=2)
    args = p.parse_args(argv)
    dataset = load_dataset(args.data)
    tc = open_texcoords(args.texcoords, dataset.num_vertices)
    args.work.mkdir(parents=True, exist_ok=True)
    runs: dict[str, list] = {"geometry": [], "camera": []}
    for i in range(args.repeats):
        runs["geometry"].append(timed(lambda: train_geometry(dataset, args.work / f"geometry{i}", progress=False,
                                                             overwrite=True)))
        runs["camera"].append(timed(lambda: train(dataset, tc, args.work / f"camera{i}", camera=args.camera,
                                                  options=TrainOptions(arch="gp"), progress=False, overwrite=True)))
        print(json.dumps({k: v[-1] for k, v in runs.items()}), flush=True)
    summary = {"data": str(args.data), "train_poses": len(dataset.split["train"]), "camera": args.camera,
               "runs": runs, "cpu_s_min": {k: min(r["cpu_s"] for r in v) for k, v in runs.items()}}
    print(json.dumps(summary, indent=1))
    return summary


if __name__ == "__main__":
    main()
