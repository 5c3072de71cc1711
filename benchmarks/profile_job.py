"""Where one raster sliding job's time goes: timers around each step of the raster path
(`mvtex.sliding.hits.find_hits_raster` + `displacement_from_hits`) on the jobs of a dataset, in
one process, after a warm-up.

    python benchmarks/profile_job.py DATASET [--rig stereo] [--poses 0:40] [--repeats 2]

Prints a Markdown table (milliseconds per job and share of the job), the machine and the
command. The steps are timed by wrapping the functions named in the table for the run;
"projections, owned faces, candidate set" and "T_N, rejection rules, bookkeeping" are what
remains of the hit search and of the displacement step around the timed calls.
"""

from __future__ import annotations

import argparse
import os
import platform
import shlex
import time
from contextlib import contextmanager

import numpy as np

import mvtex.render.raster
import mvtex.sliding.fill
import mvtex.sliding.hits
import mvtex.sliding.pose
from mvtex.data.dataset import load_dataset, reference_shape
from mvtex.data.rig import as_rig
from mvtex.render.context import GLContext
from mvtex.sliding.hits import find_hits_raster
from mvtex.sliding.options import SlideOptions
from mvtex.sliding.pose import displacement_from_hits
from mvtex.sliding.topology import build_topology

TIMED = {  # step -> (the module that calls it, the function's name there) whose calls are summed
    "raster": (mvtex.sliding.hits, "rasterize_pair"),
    "occluder": (mvtex.sliding.hits, "nearest_occluder"),
    "first_hits": (mvtex.sliding.hits, "first_hits"),
    "inside": (mvtex.sliding.hits, "compiled_seen_from_inside"),
    "fill": (mvtex.sliding.pose, "fill"),
    "solve": (mvtex.sliding.fill, "solve_spd"),
}


@contextmanager
def timers(totals: dict):
    """Wrap the TIMED functions so that their calls add seconds to `totals`."""
    saved = {}
    for step, (module, name) in TIMED.items():
        fn = saved[step] = getattr(module, name)

        def timed(*args, _fn=fn, _step=step, **kwargs):
            start = time.perf_counter()
            try:
                return _fn(*args, **kwargs)
            finally:
                totals[_step] = totals.get(_step, 0.0) + time.perf_counter() - start

        setattr(module, name, timed)
    try:
        yield
    finally:
        for step, (module, name) in TIMED.items():
            setattr(module, name, saved[step])


def main(dataset: str, rig_spec: str, spec: str, repeats: int) -> tuple[str, dict]:
    """Returns the Markdown report and the milliseconds per job of each timed step and
    of the rows."""
    ds = load_dataset(dataset)
    rig = as_rig(rig_spec)
    poses = ds.select(spec)
    options = SlideOptions(subdiv=1)
    topo = build_topology(ds.faces, ds.uv, reference_shape(ds), options.subdiv)
    faces = np.asarray(ds.faces, np.int64)
    jobs = [(k, cam) for k in poses for cam in rig]
    totals: dict = {}

    def job(ctx, k, cam):
        gt, inferred = np.asarray(ds.gt[k], np.float64), np.asarray(ds.inferred[k], np.float64)
        start = time.perf_counter()
        X = topo.positions(inferred)
        hits_start = time.perf_counter()
        hits = find_hits_raster(ctx, gt, inferred, faces, X, topo, cam, options)
        disp_start = time.perf_counter()
        displacement_from_hits(hits, faces, ds.uv, X, topo, options)
        end = time.perf_counter()
        for step, seconds in (("positions", hits_start - start), ("hits", disp_start - hits_start),
                              ("displacement", end - disp_start), ("job", end - start)):
            totals[step] = totals.get(step, 0.0) + seconds

    with GLContext() as ctx:
        renderer = ctx.renderer
        for k, cam in jobs[:4]:  # compile the kernels, make the GL buffers
            job(ctx, k, cam)
        totals.clear()
        with timers(totals):
            for _ in range(repeats):
                for k, cam in jobs:
                    job(ctx, k, cam)
    n = repeats * len(jobs)
    ms = {step: 1e3 * seconds / n for step, seconds in totals.items()}
    rows = [
        ("the pair raster on llvmpipe (`render.raster.rasterize_pair`)", ms["raster"]),
        (f"harmonic fill (`sliding.fill.fill`), of which CHOLMOD (`sliding.fill.solve_spd`) {ms['solve']:.1f} ms",
         ms["fill"]),
        ("candidate windows and exact ray/triangle tests (`sliding.kernels.nearest_occluder`, `first_hits`)",
         ms["occluder"] + ms["first_hits"]),
        ("projections, owned faces, candidate set (rest of `find_hits_raster`)",
         ms["hits"] - ms["raster"] - ms["occluder"] - ms["first_hits"] - ms["inside"]),
        ("vertex normals for the inside test (`sliding.kernels.seen_from_inside`)", ms["inside"]),
        ("T_N, rejection rules, bookkeeping, subdivided positions", ms["displacement"] - ms["fill"] + ms["positions"]),
    ]
    ms["rows"] = [value for _, value in rows]
    table = "\n".join(f"| {label} | {value:.1f} | {100 * value / ms['job']:.0f} % |" for label, value in rows)
    command = shlex.join(["python", "benchmarks/profile_job.py", dataset, "--rig", rig_spec, "--poses", spec,
                          "--repeats", str(repeats)])
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return (f"Machine: {platform.platform()}, {os.cpu_count()} logical cores, GL {renderer}, load average "
            f"{load:.1f} at the end; {n} jobs, {ms['job']:.1f} ms a job\n\nCommand: `{command}`\n\n"
            f"| step | ms | share |\n|---|---|---|\n{table}"), ms


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset")
    parser.add_argument("--rig", default="stereo")
    parser.add_argument("--poses", default="0:40")
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    print(main(args.dataset, args.rig, args.poses, args.repeats)[0])
