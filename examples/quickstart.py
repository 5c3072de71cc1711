"""Quickstart: the mvtex pipeline from Python, on the built-in garment.

    python examples/quickstart.py [OUT] [NUM_POSES]

Synthesizes a small dataset, slides texture coordinates for a stereo rig, measures the
per-pixel error against the inferred baseline, and reconstructs one pose in 3-D from the
four cameras of a square rig (PLY + COLMAP model). Every step is also a CLI command.
"""

import sys
from pathlib import Path

from mvtex.data.dataset import load_dataset
from mvtex.data.rig import builtin_rig_path, load_rig
from mvtex.data.texcoords import open_texcoords
from mvtex.evaluation.evaluate import evaluate
from mvtex.recon.pose import triangulate_pose
from mvtex.sliding.dataset import slide_dataset
from mvtex.sliding.options import SlideOptions
from mvtex.synth.generate import SynthOptions, write_synth


def main(out: Path, num_poses: int) -> dict:
    write_synth(out / "shirt", SynthOptions(num_poses=num_poses))          # mvtex synth
    dataset = load_dataset(out / "shirt")
    stereo = load_rig(builtin_rig_path("stereo"))
    square = load_rig(builtin_rig_path("square4"))
    pose = dataset.split["test"][0]

    slide_dataset(dataset, stereo, out / "ts_stereo", poses=dataset.select("test"),
                  options=SlideOptions(subdiv=1), progress=False)          # mvtex slide
    tc = open_texcoords(out / "ts_stereo", dataset.num_vertices)
    error = evaluate(dataset, stereo, tc, heatmaps=out / "heatmaps", progress=False)   # mvtex eval
    print(f"SqrtMSE: inferred {error['sqrt_mse']['inferred']['mean']:.4f}, "
          f"texture sliding {error['sqrt_mse']['texcoords']['mean']:.4f}, ratio {error['ratio']:.2f}")

    slide_dataset(dataset, square, out / "ts_square4", poses=[pose], options=SlideOptions(subdiv=1), progress=False)
    report = triangulate_pose(dataset, square, open_texcoords(out / "ts_square4", dataset.num_vertices), pose,
                              out / "reconstruction", progress=False)                  # mvtex triangulate
    print(f"pose {pose}: RMSE on triangulated vertices {report['rmse_triangulated_m']['inferred'] * 1e3:.2f} mm "
          f"(inferred) -> {report['rmse_triangulated_m']['reconstructed'] * 1e3:.2f} mm (reconstructed)")
    print(f"open {out / 'reconstruction' / 'reconstruction.ply'} or the COLMAP model in {out / 'reconstruction' / 'colmap'}")
    return {"eval": error, "reconstruction": report}


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "quickstart-out"), int(sys.argv[2]) if len(sys.argv) > 2 else 40)
