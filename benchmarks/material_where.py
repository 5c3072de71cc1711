"""Where the material error of a texcoord set is: pixels whose inferred surface lies in
another UV chart than gt's, against all the others.

    python benchmarks/material_where.py DATA TEXCOORDS [--rig RIG] [--poses SPEC] [--picture PNG]

Every image of the texcoord set (its poses, or --poses, and its cameras) is evaluated as
`mvtex eval` does (`mvtex.evaluation.evaluate.ImageEvaluator`: the body in the renders,
the pixels where both show cloth). At a pixel where the inferred mesh's triangle belongs to
another chart than gt's (along a silhouette, gt shows the front piece while the inferred
mesh already shows the back one), the texcoords of one triangle cannot name the material
gt shows, which lies across the garment: such a pixel costs tens of centimetres. Prints,
mean over images: the material RMSE of eval (baseline and texcoords), the same RMSE
without those pixels, the share of pixels they are and the share of the texcoords' squared
material error they carry. --picture writes the image where they carry the most: the
texcoords' material error (blue 0 -> red >= 20 mm, the body grey, those pixels magenta)
and a 4x enlargement around them.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def _rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(values * values))) if values.size else float("nan")


def image_figures(errors) -> dict:
    """The figures of one `ImageErrors`."""
    other = errors.other_chart
    sq = errors.mat_t * errors.mat_t
    return {"baseline_mm": 1e3 * _rms(errors.mat_b), "texcoords_mm": 1e3 * _rms(errors.mat_t),
            "baseline_same_chart_mm": 1e3 * _rms(errors.mat_b[~other]),
            "texcoords_same_chart_mm": 1e3 * _rms(errors.mat_t[~other]),
            "pixels": int(len(other)), "other_chart_pixels": int(other.sum()),
            "error_share": float(sq[other].sum() / sq.sum()) if sq.sum() > 0 else 0.0}


def picture(errors, camera) -> np.ndarray:
    """The texcoords' material error with the other-chart pixels, and an enlargement."""
    import cv2

    from mvtex.evaluation.material import MATERIAL_HEATMAP_MAX_MM
    from mvtex.evaluation.uv import CHART_BOUNDARY_COLOR
    from mvtex.render.pictures import heatmap, side_by_side
    from mvtex.render.shading import BODY_RGB

    raster = errors.raster
    r0, r1, c0, c1 = raster.box
    shape = (camera.height, camera.width)

    def full(flat_indices, values, fill):
        box = np.full((r1 - r0) * (c1 - c0), fill, dtype=np.asarray(values).dtype)
        box[flat_indices] = values
        return raster.full(box.reshape(r1 - r0, c1 - c0), shape, fill)

    image = heatmap(full(errors.pixels, (1e3 * errors.mat_t).astype(np.float32), np.float32(np.nan)),
                    MATERIAL_HEATMAP_MAX_MM)
    image[full(errors.body_pixels, True, False)] = BODY_RGB
    other = full(errors.pixels[errors.other_chart], True, False)
    image[other] = CHART_BOUNDARY_COLOR
    rows, cols = np.nonzero(other)
    size = camera.height // 4
    r = int(np.clip(np.median(rows) - size // 2, 0, camera.height - size)) if rows.size else 0
    c = int(np.clip(np.median(cols) - size // 2, 0, camera.width - size)) if cols.size else 0
    zoom = cv2.resize(image[r:r + size, c:c + size], (camera.width, camera.height), interpolation=cv2.INTER_NEAREST)
    framed = image.copy()
    cv2.rectangle(framed, (c, r), (c + size - 1, r + size - 1), (255, 255, 255), 1)
    return side_by_side([framed, zoom], ["material error, texcoords (magenta: another chart)", "4x"])


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", type=Path, help="dataset directory (with a rest shape)")
    parser.add_argument("texcoords", type=Path, help="texcoord set")
    parser.add_argument("--rig", default="stereo", help="the texcoord set's rig (default stereo)")
    parser.add_argument("--poses", help="pose SPEC (default the texcoord set's poses)")
    parser.add_argument("--picture", type=Path, help="write the picture of the image they weigh most in")
    args = parser.parse_args(argv)

    from mvtex.data.dataset import load_dataset
    from mvtex.data.rig import load_rig
    from mvtex.data.texcoords import open_texcoords
    from mvtex.evaluation.evaluate import ImageEvaluator
    from mvtex.render.context import GLContext
    from mvtex.util.files import save_png

    ds = load_dataset(args.data)
    rig = load_rig(args.rig)
    tc = open_texcoords(args.texcoords, ds.num_vertices)
    poses = tc.poses if args.poses is None else [k for k in ds.select(args.poses) if k in tc.poses]
    cameras = [c for c in rig if c.name in tc.cameras]
    rows, worst = [], None
    with GLContext() as ctx:
        evaluator = ImageEvaluator(ctx, ds, tc.faces, tc.uv, tc.parent)
        for k in poses:
            for cam in cameras:
                errors = evaluator(k, cam, tc.texcoords(cam.name, k))
                figures = image_figures(errors)
                rows.append(figures)
                weight = figures["error_share"] * figures["texcoords_mm"]
                if worst is None or weight > worst[0]:
                    worst = (weight, k, cam, errors)
    mean = {key: float(np.mean([r[key] for r in rows])) for key in rows[0]}
    share = np.mean([r["other_chart_pixels"] / r["pixels"] for r in rows])
    print(f"{len(rows)} images of {args.texcoords} ({args.rig}); pixels where the inferred mesh shows another chart "
          f"than gt: {mean['other_chart_pixels']:.1f} per image ({100 * share:.3f} % of the pixels), "
          f"{100 * mean['error_share']:.1f} % of the texcoords' squared material error\n")
    print("| pixels | baseline (mm) | texcoords (mm) | ratio |\n|---|---|---|---|")
    for label, b, t in (("all (eval's material error)", mean["baseline_mm"], mean["texcoords_mm"]),
                        ("without the other-chart pixels", mean["baseline_same_chart_mm"],
                         mean["texcoords_same_chart_mm"])):
        print(f"| {label} | {b:.2f} | {t:.3f} | {b / t:.1f} |")
    if args.picture and worst is not None:
        _, k, cam, errors = worst
        save_png(args.picture, picture(errors, cam))
        print(f"\nwrote {args.picture}: pose {k}, camera {cam.name}")
    return {"images": len(rows), "mean": mean, "pixel_share": float(share)}


if __name__ == "__main__":
    main()
