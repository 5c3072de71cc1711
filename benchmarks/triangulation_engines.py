"""Both triangulation engines on the same tracks of one pose: speed and agreement.

    python benchmarks/triangulation_engines.py DATASET RIG TEXCOORDS POSE [REPEATS]

Collects the pose's observations once (`collect_hypotheses`, `screen_hypotheses`, `vote`),
then runs step 4 (`triangulate_observations`: triangulation with outlier removal) with
`engine="mvtex"` (vectorised DLT + Gauss-Newton) and `engine="pycolmap"` (COLMAP's
multi-view triangulation + points-only bundle adjustment), alternating, and prints one
JSON object: the median seconds of each, their ratio, and the largest distance between
the two engines' points.
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np

from mvtex.data.dataset import load_dataset
from mvtex.data.rig import load_rig, resolve_rig
from mvtex.data.texcoords import open_texcoords
from mvtex.recon.consensus import screen_hypotheses, vote
from mvtex.recon.locate import collect_hypotheses
from mvtex.recon.triangulate import ReconOptions, consensus_threshold, triangulate_observations


def main(dataset: str, rig: str, texcoords: str, pose: int, repeats: int = 5) -> dict:
    ds = load_dataset(dataset)
    tc = open_texcoords(texcoords, ds.num_vertices)
    full_rig = load_rig(resolve_rig(rig))
    cameras = [full_rig[c] for c in tc.cameras if c in full_rig.names]
    X_N = tc.positions(np.asarray(ds.inferred[pose], np.float64))
    T = {c.name: np.asarray(tc.texcoords(c.name, pose), np.float64) for c in cameras}
    assigned = {c.name: tc.assigned(c.name, pose) for c in cameras}
    options = ReconOptions()
    hypotheses, _ = collect_hypotheses(ds.uv, X_N, tc.faces, T, cameras, uv_resolution=options.uv_resolution,
                                       assigned=assigned)
    hypotheses, _ = screen_hypotheses(hypotheses, tc.faces, tc.uv, [T[c.name] for c in cameras], options.max_stretch)
    threshold = consensus_threshold(hypotheses, ds.num_vertices, cameras, options)
    voted = vote(hypotheses, ds.num_vertices, cameras, threshold, options.max_combinations, options.refine_iterations)
    pixels, weights = voted.pixels, voted.weights

    seconds: dict[str, list[float]] = {"mvtex": [], "pycolmap": []}
    points = {}
    for _ in range(repeats):
        for engine in seconds:
            start = time.perf_counter()
            X, _, _ = triangulate_observations(cameras, pixels, weights, ReconOptions(engine=engine))
            seconds[engine].append(time.perf_counter() - start)
            points[engine] = X
    both = np.all(np.isfinite(points["mvtex"]), axis=1)
    median = {engine: float(np.median(s)) for engine, s in seconds.items()}
    return {"pose": pose, "cameras": len(cameras), "tracks": int(both.sum()),
            "observations": int((weights[both] > 0).sum()), "median_seconds": median,
            "pycolmap_over_mvtex": median["pycolmap"] / median["mvtex"],
            "max_difference_m": float(np.abs(points["mvtex"][both] - points["pycolmap"][both]).max()),
            "same_tracks_triangulated": bool(np.array_equal(both, np.all(np.isfinite(points["pycolmap"]), axis=1)))}


if __name__ == "__main__":
    args = sys.argv[1:]
    print(json.dumps(main(args[0], args[1], args[2], int(args[3]), *(int(a) for a in args[4:5])), indent=2))
