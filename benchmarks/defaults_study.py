"""Choose `slide`'s defaults by held-out accuracy on both built-in garments.

For the shirt and the skirt (small datasets, their test split), texture sliding runs with
subdivision 0 and 1 for the current defaults and for each candidate, one factor changed at
a time: edge breaking off/4/8, fill harmonic/fmm, candidate radius 1/2, depth tolerance
1e-3/1e-2, cross-chart hits off/on. Each run is evaluated from the stereo and square4 rigs'
cameras together, and a markdown table per rig is printed: the paper's metric (SqrtMSE
ratio inferred / TS, all pixels and same-chart pixels) and the material error in
millimeters (and its ratio inferred / TS for one subdivision).

    nice -n 10 python benchmarks/defaults_study.py [--poses 60] [--out DIR] [--json FILE]

About 10 minutes on two CPU cores.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from mvtex.data.dataset import load_dataset
from mvtex.data.rig import Rig, load_rig, resolve_rig
from mvtex.evaluation.evaluate import evaluate
from mvtex.sliding.dataset import slide_dataset
from mvtex.sliding.options import SlideOptions
from mvtex.synth.generate import SynthOptions, write_synth

# One factor at a time around the defaults: (label, SlideOptions changes).
CANDIDATES = [
    ("defaults", {}),
    ("break ratio off", {"break_ratio": None}),
    ("break ratio 4", {"break_ratio": 4.0}),
    ("break ratio 8", {"break_ratio": 8.0}),
    ("fill fmm", {"fill": "fmm"}),
    ("fill harmonic", {"fill": "harmonic"}),
    ("radius 2", {"radius": 2}),
    ("radius 1", {"radius": 1}),
    ("depth tolerance 1e-2", {"depth_tolerance": 1e-2}),
    ("depth tolerance 1e-3", {"depth_tolerance": 1e-3}),
    ("cross-chart on", {"cross_chart": True}),
    ("cross-chart off", {"cross_chart": False}),
]


def candidates(defaults: SlideOptions) -> list[tuple[str, dict]]:
    """The candidate list without the ones equal to the defaults (measured once, as "defaults")."""
    out = []
    for label, changes in CANDIDATES:
        if changes and all(getattr(defaults, k) == v for k, v in changes.items()):
            continue
        out.append((label, changes))
    return out


def study(work: Path, num_poses: int, garments: list[str], rig_names: list[str],
          only: list[str] | None = None) -> list[dict]:
    rig = Rig(tuple(cam for name in rig_names for cam in load_rig(resolve_rig(name))))
    defaults = SlideOptions()
    rows = []
    for garment in garments:
        data = work / garment
        if not data.exists():
            write_synth(data, SynthOptions(num_poses=num_poses, garment=garment))
        dataset = load_dataset(data)
        test = dataset.split["test"]
        for label, changes in candidates(defaults):
            if only and label not in only:
                continue
            row = {"garment": garment, "candidate": label, "options": changes}
            for subdiv in (0, 1):
                options = replace(defaults, subdiv=subdiv, **changes)
                start = time.perf_counter()
                out = work / "runs" / f"{garment}_{label.replace(' ', '_')}_s{subdiv}"
                tc = slide_dataset(dataset, rig, out, poses=test, options=options, workers=1, progress=False)
                result = evaluate(dataset, rig, tc, progress=False).to_json()
                row[f"subdiv{subdiv}"] = {name: _per_rig(result, [c.name for c in load_rig(resolve_rig(name))])
                                          for name in rig_names}
                print(f"{garment:6s} {label:22s} subdiv {subdiv}: " + "; ".join(
                    f"{name} ratio {r['ratio']:.2f}, same-chart {r['ratio_same_chart']:.1f}, material "
                    f"{r['material_mm']['texcoords']:.3f} mm" for name, r in row[f"subdiv{subdiv}"].items())
                    + f" ({time.perf_counter() - start:.0f} s)", file=sys.stderr)
            rows.append(row)
    return rows


def _per_rig(result: dict, cameras: list[str]) -> dict:
    """Means over one rig's cameras (each camera has the same images, so the camera means
    average to the mean over the rig's images) and the ratios of those means."""
    per = [result["per_camera"][c] for c in cameras]

    def mean(key: str, which: str) -> float:
        return float(np.mean([p[key][which]["mean"] for p in per]))

    out = {"num_images": int(sum(p["num_images"] for p in per))}
    for key, ratio in (("sqrt_mse", "ratio"), ("sqrt_mse_same_chart", "ratio_same_chart"),
                       ("material_rmse_m", "ratio_material")):
        out[key] = {w: mean(key, w) for w in ("inferred", "texcoords")}
        out[ratio] = out[key]["inferred"] / out[key]["texcoords"]
    out["material_mm"] = {w: 1e3 * v for w, v in out["material_rmse_m"].items()}
    return out


def markdown(rows: list[dict], rig_names: list[str]) -> str:
    lines = []
    for rig in rig_names:
        lines += [f"\n**{rig}**\n", "| garment | candidate | TS ratio | TS same-chart ratio | TS material mm | "
                  "TS+1 ratio | TS+1 same-chart ratio | TS+1 material mm | TS+1 material ratio |",
                  "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
        for row in rows:
            cells = [row["garment"], row["candidate"]]
            for subdiv in (0, 1):
                r = row[f"subdiv{subdiv}"][rig]
                cells += [f"{r['ratio']:.2f}", f"{r['ratio_same_chart']:.1f}", f"{r['material_mm']['texcoords']:.3f}"]
            cells.append(f"{row['subdiv1'][rig]['ratio_material']:.1f}")
            lines.append("| " + " | ".join(cells) + " |")
        for garment in sorted({row["garment"] for row in rows}):
            base = next(r for r in rows if r["garment"] == garment)["subdiv0"][rig]
            lines.append(f"\n{garment}, {rig}: inferred mesh (baseline) material error "
                         f"{base['material_mm']['inferred']:.2f} mm, "
                         f"SqrtMSE {1e3 * base['sqrt_mse']['inferred']:.2f}e-3, "
                         f"{base['num_images']} images")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--poses", type=int, default=60, help="poses per garment dataset (default 60)")
    parser.add_argument("--out", type=Path, help="work directory (default: a temporary one)")
    parser.add_argument("--garments", default="shirt,skirt")
    parser.add_argument("--rigs", default="stereo,square4")
    parser.add_argument("--json", type=Path, help="also write the rows as JSON here")
    parser.add_argument("--candidates", help="comma-separated candidate labels to run (default: all)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = args.out or Path(tmp)
        rows = study(work, args.poses, args.garments.split(","), args.rigs.split(","),
                     args.candidates.split(",") if args.candidates else None)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")
    print(markdown(rows, args.rigs.split(",")))


if __name__ == "__main__":
    main()
