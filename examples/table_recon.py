"""Reconstruction accuracy on the built-in garment: RMSE of the inferred mesh and of the
triangulated reconstruction (all vertices, triangulated vertices), per rig and subdivision.

    python examples/table_recon.py WORKDIR [POSES_SPEC] [RIG ...]

Defaults: the first 6 test poses, rigs square4 and trapezoid12, TS texcoords.
"""

import sys
from pathlib import Path

import numpy as np

from mvtex.data.dataset import load_dataset
from mvtex.data.rig import builtin_rig_path, load_rig
from mvtex.data.texcoords import open_texcoords
from mvtex.recon.pose import triangulate_pose
from mvtex.sliding.dataset import slide_dataset
from mvtex.sliding.options import SlideOptions
from mvtex.synth.generate import SynthOptions, write_synth


def main(work: Path, spec: str | None = None, rigs: tuple[str, ...] = ("square4", "trapezoid12")) -> str:
    if not (work / "shirt" / "dataset.json").exists():
        write_synth(work / "shirt", SynthOptions())
    dataset = load_dataset(work / "shirt")
    poses = dataset.select(spec) if spec else dataset.split["test"][:6]
    lines = ["| rig | subdiv | triangulated / vertices | RMSE all: inferred → reconstructed (mm) "
             "| RMSE triangulated: inferred → reconstructed (mm) | ratio (triangulated) | reprojection (px) |",
             "|---|---|---|---|---|---|---|"]
    for rig_name in rigs:
        rig = load_rig(builtin_rig_path(rig_name))
        for subdiv in (0, 1):
            tc_path = work / f"recon_{rig_name}_s{subdiv}"
            slide_dataset(dataset, rig, tc_path, poses=poses, options=SlideOptions(subdiv=subdiv), workers=2)
            tc = open_texcoords(tc_path, dataset.num_vertices)
            reports = [triangulate_pose(dataset, rig, tc, k, None, progress=False) for k in poses]
            mean = lambda f: float(np.mean([f(r) for r in reports]))  # noqa: E731
            tri = mean(lambda r: r["num_triangulated"])
            a_i, a_r = mean(lambda r: r["rmse_m"]["inferred"]) * 1e3, mean(lambda r: r["rmse_m"]["reconstructed"]) * 1e3
            t_i = mean(lambda r: r["rmse_triangulated_m"]["inferred"]) * 1e3
            t_r = mean(lambda r: r["rmse_triangulated_m"]["reconstructed"]) * 1e3
            rep = mean(lambda r: r["mean_reprojection_error_px"])
            lines.append(f"| {rig_name} | {subdiv} | {tri:.0f} / {dataset.num_vertices} | {a_i:.2f} → {a_r:.2f} "
                         f"| {t_i:.2f} → {t_r:.3f} | {t_i / t_r:.1f}× | {rep:.3f} |")
    table = "\n".join(lines)
    print(f"poses {poses}\n{table}")
    return table


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "recon-work"), sys.argv[2] if len(sys.argv) > 2 else None,
         tuple(sys.argv[3:]) or ("square4", "trapezoid12"))
