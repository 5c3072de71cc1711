"""Texture sliding at paper scale: build an N-pose dataset of the built-in garment (3,102
vertices; 1 subdivision -> 12,090 sliding vertices; 512x512 cameras) and slide it on the
`stereo` rig (every pose) and the `trapezoid12` rig (a few poses) with 1 and 2 worker
processes and on a Dask LocalCluster, through the command line a user runs.

    python benchmarks/paper_scale.py WORK [--poses N] [--trapezoid-poses P] [--workers 1,2,dask:2]

Defaults: N = 10,000 poses, P = 4, workers 1, 2 and dask:2. A `dask:W` entry starts a
`dask.distributed.LocalCluster` of W single-threaded worker processes in this script and
runs `mvtex slide ... --scheduler ADDRESS` against it; the entries run in the order given.
WORK must not hold earlier results of this script (sliding resumes, which would make the
timing meaningless). Prints a Markdown table (each row also goes to stderr as soon as it
is measured): throughput in (pose, camera) jobs/s including process start-up, peak
resident memory of the whole process tree (the command and its workers, summed, sampled
every 0.1 s; for a Dask row also this script, which holds the scheduler, and the cluster's
worker processes), the peak of its anonymous part (resident memory minus file-backed and
shared pages: what memory-mapped files and shared libraries do not account for) and the
projected time for 10,000 poses x 12 cameras at the measured rate, with the machine, its
load average and the commands. Resident memory is sampled with psutil (installed with
mvtex[dist]).
"""

from __future__ import annotations

import argparse
import os
import platform
import shlex
import subprocess
import sys
import time
from pathlib import Path

import psutil

PROJECTED_JOBS = 10_000 * 12


def run_measured(argv: list[str], whole_script: bool = False) -> tuple[float, float, float]:
    """Run a command; return (wall seconds, peak summed RSS of it and its descendants in
    GiB, peak summed anonymous RSS in GiB); with whole_script, of this process and all its
    descendants instead. Anonymous = RSS minus shared (file-backed and shared-memory) pages,
    NaN where psutil does not report shared pages."""
    start = time.perf_counter()
    proc = subprocess.Popen(argv)
    root = psutil.Process(os.getpid() if whole_script else proc.pid)
    peak = peak_anon = 0
    while proc.poll() is None:
        total = anon = 0
        try:
            for p in [root, *root.children(recursive=True)]:
                try:
                    info = p.memory_info()
                    total += info.rss
                    anon += info.rss - getattr(info, "shared", float("nan"))
                except psutil.NoSuchProcess:
                    pass
        except psutil.NoSuchProcess:
            pass
        peak, peak_anon = max(peak, total), max(peak_anon, anon)
        time.sleep(0.1)
    seconds = time.perf_counter() - start
    if proc.returncode != 0:
        raise SystemExit(f"command failed with exit code {proc.returncode}: {shlex.join(argv)}")
    return seconds, peak / 2**30, peak_anon / 2**30


def machine() -> str:
    model = platform.processor() or "unknown CPU"
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
        model = next(line.split(":", 1)[1].strip() for line in out.splitlines() if line.startswith("Model name"))
    except (OSError, subprocess.CalledProcessError, StopIteration):
        pass
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return f"{model}, {os.cpu_count()} logical cores, load average {load:.1f} at the end"


def slide_row(rig: str, workers: str, poses: int, seconds: float, jobs: int, peak: tuple[float, float]) -> str:
    rate = jobs / seconds
    projected = PROJECTED_JOBS / rate / 3600
    return (f"| slide `{rig}`, poses 0:{poses} | {workers} | {seconds:.1f} s | {rate:.1f} | {peak[0]:.2f} | "
            f"{peak[1]:.2f} | {projected:.1f} h |")


def main(work: Path, poses: int = 10_000, trapezoid_poses: int = 4,
         workers: tuple[str, ...] = ("1", "2", "dask:2")) -> str:
    workers = tuple(str(w) for w in workers)
    mvtex = [sys.executable, "-m", "mvtex"]
    data = work / "data"
    runs = [("synth", None, None, [*mvtex, "synth", "--out", str(data), "--num-poses", str(poses)], 0, 0)]
    for rig, count, cams in (("stereo", poses, 2), ("trapezoid12", min(trapezoid_poses, poses), 12)):
        for w in workers:
            out = work / f"{rig}_w{w.replace(':', '')}"
            argv = [*mvtex, "slide", str(data), "--rig", rig, "--poses", f"0:{count}", "--out", str(out), "--quiet"]
            if not w.startswith("dask:"):
                argv += ["--workers", w]
            runs.append(("slide", rig, w, argv, count, count * cams))
    for *_, argv, _, _ in runs:
        target = Path(argv[argv.index("--out") + 1]) if "--out" in argv else data
        if target.exists() or Path(str(target) + ".partial").exists():
            raise SystemExit(f"{target}: exists; use a fresh WORK directory")
    rows = []
    loads = []
    for kind, rig, w, argv, count, jobs in runs:
        if kind == "synth":
            print("$", shlex.join(argv), file=sys.stderr, flush=True)
            seconds, *peak = run_measured(argv)
            rows.append(f"| synth {poses} poses | – | {seconds:.1f} s | – | {peak[0]:.2f} | {peak[1]:.2f} | – |")
        elif w.startswith("dask:"):
            from dask.distributed import LocalCluster

            n = int(w.split(":", 1)[1])
            with LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
                argv = [*argv, "--scheduler", cluster.scheduler_address]
                print("$", shlex.join(argv), file=sys.stderr, flush=True)
                seconds, *peak = run_measured(argv, whole_script=True)
            rows.append(slide_row(rig, f"Dask LocalCluster, {n} processes", count, seconds, jobs, peak))
        else:
            print("$", shlex.join(argv), file=sys.stderr, flush=True)
            seconds, *peak = run_measured(argv)
            rows.append(slide_row(rig, w, count, seconds, jobs, peak))
        loads.append(os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan"))
        print(rows[-1], f"(load average {loads[-1]:.1f})", file=sys.stderr, flush=True)
    header = ("| run | workers | wall time | jobs/s | peak RSS of the process tree (GiB) | of which anonymous (GiB) "
              "| 10,000 poses × 12 cameras at this rate |\n|---|---|---|---|---|---|---|")
    command = shlex.join(["python", "benchmarks/paper_scale.py", str(work), "--poses", str(poses),
                          "--trapezoid-poses", str(trapezoid_poses), "--workers", ",".join(workers)])
    return (f"Machine: {machine()}; 1-minute load average after each run: {', '.join(f'{x:.1f}' for x in loads)}"
            f"\n\nCommand: `{command}`\n\n{header}\n" + "\n".join(rows))


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("work", type=Path, help="directory for the dataset and the texcoord sets")
    parser.add_argument("--poses", type=int, default=10_000, help="poses of the dataset, all slid on stereo")
    parser.add_argument("--trapezoid-poses", type=int, default=4, help="poses slid on trapezoid12")
    parser.add_argument("--workers", default="1,2,dask:2",
                        help="comma-separated runs to measure, in order: N local worker processes, "
                             "or dask:W for a Dask LocalCluster of W processes")
    args = parser.parse_args()
    workers = tuple(w.strip() for w in args.workers.split(","))
    for w in workers:
        if not (w.isdigit() and int(w) > 0) and not (w.startswith("dask:") and w[5:].isdigit() and int(w[5:]) > 0):
            parser.error(f"--workers: {w!r} is neither a worker count nor dask:W")
    print(main(args.work, args.poses, args.trapezoid_poses, workers))
