"""Peak memory of `mvtex triangulate` against the number of cameras.

Builds the built-in shirt (`--num-poses` poses), a ring of C cameras of 64x64 pixels
around it at its height, and a texcoord set of those cameras with zero displacement (every
camera sees the inferred mesh as it is: the reconstruction's full work, none of the
sliding's), then runs `mvtex triangulate` on pose 0 for each C in its own process and
reports the process's peak resident memory (`getrusage` of the child) and its wall time.

    python benchmarks/triangulate_memory.py /tmp/trimem --cameras 50,200
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import mvtex
from mvtex.data.camera import look_at
from mvtex.data.texcoords import rig_record


def ring(centre: np.ndarray, count: int) -> mvtex.Rig:
    cameras = []
    for i in range(count):
        a = 2 * np.pi * i / count
        eye = centre + np.array([1.5 * np.sin(a), 0.3 * np.sin(7 * a), 1.5 * np.cos(a)])
        cameras.append(look_at(f"c{i:04d}", eye, centre, width=64, height=64, focal=60.0))
    return mvtex.Rig(tuple(cameras))


def setup(root: Path, count: int, num_poses: int) -> tuple[Path, Path, Path]:
    """(dataset, rig file, texcoord set) for `count` cameras, made once under `root`."""
    data = root / "shirt"
    if not (data / "dataset.json").exists():
        mvtex.write_synth(data, mvtex.SynthOptions(num_poses=num_poses), progress=False)
    dataset = mvtex.load_dataset(data)
    rig = ring(np.asarray(dataset.gt[0], np.float64).mean(axis=0), count)
    rig_file, texcoords = root / f"ring{count}.yaml", root / f"tc{count}"
    if not rig_file.exists():
        mvtex.save_rig(rig, rig_file)
    if not texcoords.exists():
        n = dataset.num_vertices
        mvtex.save_texcoords(texcoords, faces=dataset.faces, uv=dataset.uv, parent=np.stack([np.arange(n)] * 2, 1),
                             source="ts", subdiv=0, poses=[0],
                             displacement={c.name: np.zeros((1, n, 2), np.float32) for c in rig},
                             assigned={c.name: np.ones((1, n), bool) for c in rig}, rig=rig_record(rig))
    return data, rig_file, texcoords


def measure(data: Path, rig_file: Path, texcoords: Path, out: Path) -> dict:
    """Peak resident memory (MB) and wall time (s) of one `mvtex triangulate` process."""
    start = time.perf_counter()
    with tempfile.TemporaryFile() as stdout, tempfile.TemporaryFile() as stderr:
        proc = subprocess.Popen([sys.executable, "-m", "mvtex", "triangulate", str(data), "--rig", str(rig_file),
                                 "--texcoords", str(texcoords), "--pose", "0", "--out", str(out), "--overwrite",
                                 "--quiet", "--json"], stdout=stdout, stderr=stderr)
        _, status, usage = os.wait4(proc.pid, 0)  # the child's own rusage: its peak resident set
        proc.returncode = os.waitstatus_to_exitcode(status)
        stdout.seek(0)
        stderr.seek(0)
        if proc.returncode != 0:
            raise SystemExit(stderr.read().decode())
        report = json.loads(stdout.read())
    return {"peak_rss_mb": round(usage.ru_maxrss / 1024, 1), "seconds": round(time.perf_counter() - start, 1),
            "num_triangulated": report["num_triangulated"]}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("root", type=Path, help="working folder (reused: the data is made once)")
    parser.add_argument("--cameras", default="50,200", help="camera counts, comma-separated (default 50,200)")
    parser.add_argument("--num-poses", type=int, default=10, help="poses of the built-in shirt (default 10)")
    args = parser.parse_args(argv)
    args.root.mkdir(parents=True, exist_ok=True)
    rows = {}
    for count in (int(c) for c in args.cameras.split(",")):
        data, rig_file, texcoords = setup(args.root, count, args.num_poses)
        rows[count] = measure(data, rig_file, texcoords, args.root / f"rec{count}")
        print(f"{count} cameras: peak {rows[count]['peak_rss_mb']} MB, {rows[count]['seconds']} s, "
              f"{rows[count]['num_triangulated']} vertices triangulated", flush=True)
    return rows


if __name__ == "__main__":
    main()
