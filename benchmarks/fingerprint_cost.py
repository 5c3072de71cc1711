"""What the content fingerprint in slide's resume key costs, next to the slide it protects.

`mvtex slide` hashes gt.npy, inferred.npy and poses.npy (BLAKE2b, memory-mapped, in
16 MB blocks) so that arrays replaced in place restart a run instead of being mixed into
it. This script times that hash on a synthetic memory-mapped dataset of K poses of a
3,102-vertex garment (the built-in one's size) next to a plain read of the same bytes.

    python benchmarks/fingerprint_cost.py --poses 2000
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from mvtex.util.fingerprint import fingerprint


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=2000, help="number of poses (default 2000)")
    parser.add_argument("--vertices", type=int, default=3102, help="vertices per pose (default 3102)")
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats (default 3)")
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        arrays = []
        for name, shape in (("gt", (args.poses, args.vertices, 3)), ("inferred", (args.poses, args.vertices, 3)),
                            ("poses", (args.poses, 12))):
            path = Path(tmp) / f"{name}.npy"
            np.save(path, rng.standard_normal(shape).astype(np.float32))
            arrays.append(np.load(path, mmap_mode="r"))
        nbytes = sum(a.nbytes for a in arrays)
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            digest = fingerprint(*arrays)
            t_hash = time.perf_counter() - t0
            t0 = time.perf_counter()
            total = sum(float(np.add.reduce(a, axis=None, dtype=np.float64)) for a in arrays)
            t_read = time.perf_counter() - t0
            print(f"{args.poses} poses, {nbytes / 1e6:.0f} MB: fingerprint {t_hash:.3f} s ({nbytes / 1e6 / t_hash:.0f} MB/s), "
                  f"plain read+sum {t_read:.3f} s, ratio {t_hash / t_read:.2f} [{digest}, {total:.3g}]")


if __name__ == "__main__":
    main()
