"""Where texture sliding's material error comes from: pixels where gt shows its inside.

    python benchmarks/material_inside.py DATA TEXCOORDS [--rig stereo] [--picture worst.png]

Splits the material error of `mvtex eval` (DESIGN §7) by what the ground-truth mesh shows
at each pixel: its outside (a front-facing gt triangle) or its inside (a back-facing one:
a view into the collar or the waist of a tube, past a hem). A texcoord set stores one uv
per vertex, so where gt shows the inside of the back panel right next to the outside of
the front panel, every inferred triangle across that boundary interpolates uv between the
two charts; `slide` leaves such vertices to the fill (DESIGN §5 step 5), and the pixels keep
the baseline's error of 0.2-0.3 m on the rest garment. Prints a Markdown table: RMSE over
all covered pixels (eval's number), over pixels where gt shows its outside, the share of
pixels and of images that show the inside; with --picture, the error image of the worst
image (blue 0 -> red >= 20 mm).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", type=Path, help="dataset directory (with rest)")
    parser.add_argument("texcoords", type=Path, help="texcoord set (TS or TSNN)")
    parser.add_argument("--rig", default="stereo", help="rig of the texcoord set (default stereo)")
    parser.add_argument("--picture", type=Path, help="write the worst image's error picture here")
    args = parser.parse_args()

    from mvtex.data.dataset import load_dataset
    from mvtex.data.mesh import face_normals
    from mvtex.data.rig import load_rig, resolve_rig
    from mvtex.data.texcoords import open_texcoords
    from mvtex.evaluation.material import MaterialMap, material_error_image
    from mvtex.render.context import GLContext
    from mvtex.render.raster import rasterize

    ds = load_dataset(args.data)
    rig = load_rig(resolve_rig(args.rig))
    tc = open_texcoords(args.texcoords, ds.num_vertices)
    rows = []
    with GLContext() as ctx:
        material = MaterialMap(ds.faces, ds.uv, ds.rest, ctx=ctx)
        for k in tc.poses:
            gt = np.asarray(ds.gt[k], np.float64)
            inferred = np.asarray(ds.inferred[k], np.float64)
            normals = face_normals(gt, ds.faces, normalize=False)
            for cam in rig:
                if cam.name not in tc.cameras:
                    continue
                base, _ = material_error_image(ctx, gt, ds.faces, ds.rest, inferred, ds.faces, ds.uv, cam, material)
                slid, _ = material_error_image(ctx, gt, ds.faces, ds.rest, tc.positions(inferred), tc.faces,
                                               tc.texcoords(cam.name, k), cam, material)
                r = rasterize(ctx, gt, ds.faces, cam)
                tri = r.tri_id[r.mask]
                inside = np.zeros(r.mask.shape, bool)  # the pixel's gt triangle faces away from the camera
                inside[r.mask] = np.einsum("ij,ij->i", normals[tri], gt[ds.faces[tri, 0]] - cam.center) > 0
                rows.append((k, cam.name, base, slid, inside))

    def rmse(images, outside_only):
        values = []
        for *_, error, inside in images:
            keep = np.isfinite(error) & (~inside if outside_only else True)
            values.append(np.sqrt(np.mean(error[keep] ** 2)) if keep.any() else np.nan)
        return float(np.nanmean(values))

    base = [(k, c, b, i) for k, c, b, _, i in rows]
    slid = [(k, c, s, i) for k, c, _, s, i in rows]
    share = np.mean([i[np.isfinite(s)].mean() for *_, s, i in rows])
    showing = sum(bool(i[np.isfinite(s)].any()) for *_, s, i in rows)
    print(f"{len(rows)} images ({args.texcoords}), gt shows its inside in {showing} of them, "
          f"{100 * share:.2f} % of the covered pixels on average\n")
    print("| pixels | inferred (mm) | texcoords (mm) | ratio |")
    print("|---|---|---|---|")
    for label, outside in (("all covered (eval's material error)", False), ("where gt shows its outside", True)):
        b, s = rmse(base, outside), rmse(slid, outside)
        print(f"| {label} | {b * 1e3:.2f} | {s * 1e3:.3f} | {b / s:.2f} |")
    if args.picture:
        import imageio.v3 as iio

        k, name, _, error, _ = max(rows, key=lambda row: np.sqrt(np.nanmean(row[3] ** 2)))
        t = np.clip(np.nan_to_num(error, nan=0.0) / 0.02, 0, 1)
        picture = (np.stack([t, np.zeros_like(t), 1 - t], -1) * 255).astype(np.uint8)
        picture[~np.isfinite(error)] = 0
        iio.imwrite(args.picture, picture)
        print(f"\nwrote {args.picture}: pose {k}, camera {name}")


if __name__ == "__main__":
    main()
