"""Bring your own cloth: OBJ sequences -> mvtex dataset -> texture sliding.

    python examples/own_data.py GT_GLOB INFERRED_GLOB OUT [RIG]

Your meshes need one connectivity and vertex order across the sequence (the same faces in
every file) and per-vertex texture coordinates (OBJ `vt`, PLY `s t`). UV seams must be
split vertices. Files are paired in sorted order. Pose vectors are optional (`mvtex import --pose-vectors FILE`).
With no arguments, the script writes a demo sequence from the built-in garment first.
"""

import sys
import tempfile
from pathlib import Path

import numpy as np

from mvtex.data.dataset import load_dataset
from mvtex.data.importer import import_sequences
from mvtex.data.rig import load_rig, resolve_rig
from mvtex.sliding.dataset import slide_dataset
from mvtex.sliding.options import SlideOptions


def write_obj(path: Path, positions: np.ndarray, uv: np.ndarray, faces: np.ndarray) -> None:
    with open(path, "w") as f:
        f.writelines(f"v {x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in positions)
        f.writelines(f"vt {u:.6f} {v:.6f}\n" for u, v in uv)
        f.writelines(f"f {a}/{a} {b}/{b} {c}/{c}\n" for a, b, c in faces + 1)


def demo_sequence(folder: Path, num_poses: int = 12) -> tuple[str, str]:
    from mvtex.synth.generate import SynthOptions, synthesize

    data = synthesize(SynthOptions(num_poses=max(num_poses, 10)))
    for k in range(num_poses):
        write_obj(folder / f"gt_{k:04d}.obj", data["gt"][k], data["uv"], data["faces"])
        write_obj(folder / f"inferred_{k:04d}.obj", data["inferred"][k], data["uv"], data["faces"])
    return str(folder / "gt_*.obj"), str(folder / "inferred_*.obj")


def main(gt_glob: str, inferred_glob: str, out: Path, rig: str = "stereo") -> Path:
    import_sequences(out / "dataset", gt_glob, inferred_glob, progress=False)   # mvtex import
    dataset = load_dataset(out / "dataset")
    print(f"imported {dataset.num_poses} poses of {dataset.num_vertices} vertices")
    tc = slide_dataset(dataset, load_rig(resolve_rig(rig)), out / "texcoords", poses=dataset.select("all"),
                       options=SlideOptions(subdiv=1), progress=False)            # mvtex slide
    print(f"texcoord set written to {tc}")
    return tc


if __name__ == "__main__":
    if len(sys.argv) >= 4:
        main(sys.argv[1], sys.argv[2], Path(sys.argv[3]), *(sys.argv[4:5]))
    else:
        work = Path(tempfile.mkdtemp(prefix="mvtex-own-data-"))
        main(*demo_sequence(work), work)
