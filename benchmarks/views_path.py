"""Novel views and stereo previews on the built-in garment: the numbers and pictures of
docs/views.md (the tables are in docs/results/accuracy.md).

    python benchmarks/views_path.py WORKDIR [--poses 60] [--docs docs]

1. synthesize the garment, texture-slide the test poses from the `stereo` and `square4` rigs;
2. the two-camera plot: SqrtMSE against t along left -> right (7 views) for the baseline,
   blend, reconstruct and TS computed directly at each view (`mvtex.views.measure`);
3. the four-camera map: 3x3 views over square4;
4. stereo previews (blend and reconstruct) of every test pose: SSIM/PSNR against gt.

Prints markdown tables; writes the pictures into --docs.
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("work", type=Path)
    parser.add_argument("--poses", type=int, default=60)
    parser.add_argument("--docs", type=Path, default=Path("docs"))
    parser.add_argument("--grid-poses", type=int, default=2)
    args = parser.parse_args()

    from mvtex.data.dataset import load_dataset
    from mvtex.data.rig import builtin_rig_file, load_rig
    from mvtex.data.texcoords import open_texcoords
    from mvtex.sliding.dataset import slide_dataset
    from mvtex.sliding.options import SlideOptions
    from mvtex.synth.generate import SynthOptions, write_synth
    from mvtex.views.cameras import between_weights, grid_weights, view_names
    from mvtex.views.measure import measure_views, plot_grid, plot_path
    from mvtex.views.preview import PreviewOptions, stereo_preview

    work = args.work
    data = work / "shirt"
    if not (data / "dataset.json").exists():
        write_synth(data, SynthOptions(num_poses=args.poses, seed=0))
    ds = load_dataset(data)
    test = ds.split["test"]
    stereo, square = load_rig(builtin_rig_file("stereo")), load_rig(builtin_rig_file("square4"))
    for name, rig, poses in (("stereo", stereo, test), ("square4", square, test[:args.grid_poses])):
        if not (work / f"ts_{name}" / "texcoords.json").exists():
            slide_dataset(ds, rig, work / f"ts_{name}", poses=poses, options=SlideOptions(subdiv=1), progress=True)
    args.docs.mkdir(parents=True, exist_ok=True)

    # 2. the two-camera plot
    weights = between_weights("left", "right", 7)
    tc = open_texcoords(work / "ts_stereo", ds.num_vertices)
    two = measure_views(ds, stereo, tc, weights, view_names(7), poses=test)
    t = [w["right"] for w in weights]
    plot_path(two, args.docs / "views_two_camera.png", t, a="left", b="right")
    (work / "two_camera.json").write_text(json.dumps(two, indent=1))
    mid = len(t) // 2
    print(f"\nTwo cameras ({len(test)} test poses, {ds.num_poses}-pose dataset), SqrtMSE e-3:\n")
    print("| method | cameras, same chart | midpoint, same chart | midpoint, all pixels |")
    print("|---|---|---|---|")
    for curve, values in two["sqrt_mse_same_chart"].items():
        print(f"| {curve} | {(values[0] + values[-1]) / 2 * 1e3:.3f} | {values[mid] * 1e3:.3f} | "
              f"{two['sqrt_mse'][curve][mid] * 1e3:.2f} |")

    # 3. the four-camera map
    corners = ["tl", "tr", "bl", "br"]
    tc4 = open_texcoords(work / "ts_square4", ds.num_vertices)
    four = measure_views(ds, square, tc4, grid_weights(*corners, 3), view_names(9), poses=test[:args.grid_poses])
    plot_grid(four, args.docs / "views_four_camera.png", 3, corners)
    (work / "four_camera.json").write_text(json.dumps(four, indent=1))
    print(f"\nFour cameras (3x3 views, {args.grid_poses} test poses), same-chart SqrtMSE e-3, centre / mean:\n")
    print("| method | centre view | mean of 9 |")
    print("|---|---|---|")
    for curve, values in four["sqrt_mse_same_chart"].items():
        print(f"| {curve} | {values[4] * 1e3:.3f} | {np.mean(values) * 1e3:.3f} |")

    # 4. stereo previews
    scores = {}
    for method in ("blend", "reconstruct"):
        rows = []
        for k in test:
            out = work / f"preview_{method}_{k}"
            report = stereo_preview(ds, stereo, tc, k, out, options=PreviewOptions(method=method), progress=False)
            rows.append([[report["eyes"][e][m][w] for e in ("left", "right")]
                         for m in ("ssim", "psnr") for w in ("inferred", "texcoords")])
        scores[method] = np.mean(np.asarray(rows), axis=(0, 2))  # ssim inf, ssim tc, psnr inf, psnr tc
    first = work / f"preview_reconstruct_{test[0]}"
    for name in ("stereo.png", "anaglyph.png", "comparison.png"):
        shutil.copyfile(first / name, args.docs / f"preview_{name}")
    print(f"\nStereo previews ({len(test)} test poses x 2 eyes, garment bounding box):\n")
    print("| eye texcoords | SSIM inferred (T_G) | SSIM texcoords | PSNR inferred (dB) | PSNR texcoords (dB) |")
    print("|---|---|---|---|---|")
    for method, s in scores.items():
        print(f"| {method} | {s[0]:.3f} | {s[1]:.3f} | {s[2]:.2f} | {s[3]:.2f} |")


if __name__ == "__main__":
    main()
