"""Quickstart: the mvtex pipeline from Python, on the built-in garment.

    python examples/quickstart.py [OUT] [NUM_POSES]

Synthesizes a small dataset, slides texture coordinates for a stereo rig, measures the
material error and the per-pixel uv error against the inferred baseline, and reconstructs
one pose in 3-D from the four cameras of a square rig (PLY + COLMAP model). Each step is
the library call behind a command of the `mvtex` command line (in the comments).
"""

import sys
from pathlib import Path

import mvtex


def main(out: Path, num_poses: int) -> dict:
    mvtex.write_synth(out / "shirt", mvtex.SynthOptions(num_poses=num_poses))      # mvtex synth
    dataset = mvtex.load_dataset(out / "shirt")
    stereo, square = mvtex.load_rig("stereo"), mvtex.load_rig("square4")           # built-in rigs
    pose = dataset.split["test"][0]

    mvtex.slide_dataset(dataset, stereo, out / "ts_stereo", poses=dataset.select("test"),
                        options=mvtex.SlideOptions(subdiv=1), progress=False)       # mvtex slide
    error = mvtex.evaluate(dataset, stereo, out / "ts_stereo", heatmaps=out / "heatmaps",
                           progress=False)                                          # mvtex eval
    if error.material_rmse_m is not None:
        print(f"material error: inferred {error.material_rmse_m.inferred.mean * 1e3:.2f} mm, "
              f"texture sliding {error.material_rmse_m.texcoords.mean * 1e3:.2f} mm (ratio {error.ratio_material:.1f})")
    print(f"SqrtMSE: inferred {error.sqrt_mse.inferred.mean:.4f}, texture sliding "
          f"{error.sqrt_mse.texcoords.mean:.4f} (ratio {error.ratio:.2f})")

    mvtex.slide_dataset(dataset, square, out / "ts_square4", poses=[pose], options=mvtex.SlideOptions(subdiv=1),
                        progress=False)
    report = mvtex.triangulate_pose(dataset, square, mvtex.open_texcoords(out / "ts_square4"), pose,
                                    out / "reconstruction", progress=False)        # mvtex triangulate
    print(f"pose {pose}: RMSE on triangulated vertices {report.rmse_triangulated_m.inferred * 1e3:.2f} mm "
          f"(inferred) -> {report.rmse_triangulated_m.reconstructed * 1e3:.2f} mm (reconstructed)")
    print(f"open {out / 'reconstruction' / 'reconstruction.ply'} or the COLMAP model in "
          f"{out / 'reconstruction' / 'colmap'}")
    return {"eval": error, "reconstruction": report}


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "quickstart-out"), int(sys.argv[2]) if len(sys.argv) > 2 else 40)
