"""The paper's Table 1 on the built-in garment: baseline vs texture sliding with 0, 1, 2
subdivision levels, per rig, as a Markdown table (with the material error beside the
paper's SqrtMSE).

    python benchmarks/table1.py WORKDIR [POSES_SPEC] [RIG ...]

Defaults: every other pose of a 300-pose dataset ('::2'), rigs stereo and square4.
Slower on a 2-core CPU: several minutes (sliding is resumable; rerun to continue).
"""

import sys
from pathlib import Path

from mvtex.data.dataset import load_dataset
from mvtex.data.rig import builtin_rig_file, load_rig
from mvtex.data.texcoords import open_texcoords
from mvtex.evaluation.evaluate import evaluate
from mvtex.sliding.dataset import slide_dataset
from mvtex.sliding.options import SlideOptions
from mvtex.synth.generate import SynthOptions, write_synth


def fmt(stat: dict) -> str:
    return f"{stat['mean'] * 1e3:.3f} ± {stat['std'] * 1e3:.3f}"


def main(work: Path, spec: str = "::2", rigs: tuple[str, ...] = ("stereo", "square4")) -> str:
    if not (work / "shirt" / "dataset.json").exists():
        write_synth(work / "shirt", SynthOptions())
    dataset = load_dataset(work / "shirt")
    poses = dataset.select(spec)
    lines = ["| rig | method | material error (mm) | ratio | SqrtMSE ×10⁻³ (all pixels) | ratio "
             "| SqrtMSE ×10⁻³ (same-chart pixels) | ratio |",
             "|---|---|---|---|---|---|---|---|"]
    for rig_name in rigs:
        rig = load_rig(builtin_rig_file(rig_name))
        for subdiv in (0, 1, 2):
            tc_path = work / f"ts_{rig_name}_s{subdiv}"
            slide_dataset(dataset, rig, tc_path, poses=poses, options=SlideOptions(subdiv=subdiv), workers=2)
            r = evaluate(dataset, rig, open_texcoords(tc_path, dataset.num_vertices), progress=True).to_json()
            if subdiv == 0:
                lines.append(f"| {rig_name} ({r['num_images']} images) | inferred (baseline) "
                             f"| {fmt(r['material_rmse_m']['inferred'])} | 1 | {fmt(r['sqrt_mse']['inferred'])} | 1 "
                             f"| {fmt(r['sqrt_mse_same_chart']['inferred'])} | 1 |")
            name = "TS" if subdiv == 0 else f"TS + {subdiv} subdivision{'s' if subdiv > 1 else ''}"
            lines.append(f"| | {name} | {fmt(r['material_rmse_m']['texcoords'])} | {r['ratio_material']:.2f} "
                         f"| {fmt(r['sqrt_mse']['texcoords'])} | {r['ratio']:.2f} "
                         f"| {fmt(r['sqrt_mse_same_chart']['texcoords'])} | {r['ratio_same_chart']:.2f} |")
    table = "\n".join(lines)
    print(table)
    return table


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "table1-work"), sys.argv[2] if len(sys.argv) > 2 else "::2",
         tuple(sys.argv[3:]) or ("stereo", "square4"))
