"""Texture sliding at paper scale: build an N-pose dataset of the built-in garment (3,102
vertices; 1 subdivision -> 12,090 sliding vertices; 512x512 cameras) and slide it on the
`stereo` rig (every pose) and the `trapezoid12` rig (a few poses) with 1 and 2 worker
processes, through the command line a user runs.

    python examples/paper_scale.py WORK [--poses N] [--trapezoid-poses P] [--workers 1,2]

Defaults: N = 10,000 poses, P = 4. WORK must not hold earlier results of this script
(sliding resumes, which would make the timing meaningless). Prints a Markdown table:
throughput in (pose, camera) jobs/s including process start-up, peak resident memory of
the whole process tree (the command and its workers, summed, sampled every 0.1 s) and the
projected time for 10,000 poses x 12 cameras at the measured rate, with the machine and
the commands. Resident memory is sampled with psutil (installed with mvtex[dist]).
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


def run_measured(argv: list[str]) -> tuple[float, float]:
    """Run a command; return (wall seconds, peak summed RSS of it and its descendants in GiB)."""
    start = time.perf_counter()
    proc = subprocess.Popen(argv)
    root = psutil.Process(proc.pid)
    peak = 0
    while proc.poll() is None:
        total = 0
        try:
            for p in [root, *root.children(recursive=True)]:
                try:
                    total += p.memory_info().rss
                except psutil.NoSuchProcess:
                    pass
        except psutil.NoSuchProcess:
            pass
        peak = max(peak, total)
        time.sleep(0.1)
    seconds = time.perf_counter() - start
    if proc.returncode != 0:
        raise SystemExit(f"command failed with exit code {proc.returncode}: {shlex.join(argv)}")
    return seconds, peak / 2**30


def machine() -> str:
    model = platform.processor() or "unknown CPU"
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
        model = next(line.split(":", 1)[1].strip() for line in out.splitlines() if line.startswith("Model name"))
    except (OSError, subprocess.CalledProcessError, StopIteration):
        pass
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return f"{model}, {os.cpu_count()} logical cores, load average {load:.1f} at the end"


def main(work: Path, poses: int = 10_000, trapezoid_poses: int = 4, workers: tuple[int, ...] = (1, 2)) -> str:
    mvtex = [sys.executable, "-m", "mvtex"]
    data = work / "data"
    runs = [("synth", None, None, [*mvtex, "synth", str(data), "--poses", str(poses)], 0)]
    for rig, count, cams in (("stereo", poses, 2), ("trapezoid12", min(trapezoid_poses, poses), 12)):
        for w in workers:
            out = work / f"{rig}_w{w}"
            argv = [*mvtex, "slide", str(data), "--rig", rig, "--poses", f"0:{count}", "--workers", str(w),
                    "--out", str(out), "--quiet"]
            runs.append(("slide", rig, w, argv, count * cams))
    for *_, argv, _ in runs:
        target = Path(argv[argv.index("--out") + 1]) if "--out" in argv else data
        if target.exists() or Path(str(target) + ".partial").exists():
            raise SystemExit(f"{target}: exists; use a fresh WORK directory")
    rows = []
    for kind, rig, w, argv, jobs in runs:
        print("$", shlex.join(argv), file=sys.stderr, flush=True)
        seconds, peak = run_measured(argv)
        if kind == "synth":
            rows.append(f"| synth {poses} poses | – | {seconds:.1f} s | – | {peak:.2f} | – |")
            continue
        rate = jobs / seconds
        projected = PROJECTED_JOBS / rate / 3600
        rows.append(f"| slide `{rig}`, poses 0:{jobs // (2 if rig == 'stereo' else 12)} | {w} | {seconds:.1f} s "
                    f"| {rate:.1f} | {peak:.2f} | {projected:.1f} h |")
    header = ("| run | workers | wall time | jobs/s | peak RSS of the process tree (GiB) | "
              "10,000 poses × 12 cameras at this rate |\n|---|---|---|---|---|---|")
    command = shlex.join(["python", "examples/paper_scale.py", str(work), "--poses", str(poses),
                          "--trapezoid-poses", str(trapezoid_poses), "--workers", ",".join(map(str, workers))])
    return f"Machine: {machine()}\n\nCommand: `{command}`\n\n{header}\n" + "\n".join(rows)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("work", type=Path, help="directory for the dataset and the texcoord sets")
    parser.add_argument("--poses", type=int, default=10_000, help="poses of the dataset, all slid on stereo")
    parser.add_argument("--trapezoid-poses", type=int, default=4, help="poses slid on trapezoid12")
    parser.add_argument("--workers", default="1,2", help="comma-separated worker counts to measure")
    args = parser.parse_args()
    print(main(args.work, args.poses, args.trapezoid_poses, tuple(int(w) for w in args.workers.split(","))))
