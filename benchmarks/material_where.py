"""Where the material error of a texcoord set is: by the pixels' place on the garment and
by what the two meshes show there.

    python benchmarks/material_where.py DATA TEXCOORDS [--rig RIG] [--poses SPEC] [--picture PNG]
                                        [--near-opening M]

Every image of the texcoord set (its poses, or --poses, and its cameras) is evaluated as
`mvtex eval` does (`mvtex.evaluation.evaluate.ImageEvaluator`: the body in the renders,
the pixels where both show cloth). Each compared pixel is put in classes, and for each the
share of the pixels, the share of the texcoords' squared material error and the median
material error there are printed (pooled over all images):

- *near an opening*: gt shows material within --near-opening (default 3 cm, on the rest
  garment) of an opening of the garment (a boundary edge of the mesh with its seam copies
  joined: collar, hem, sleeve ends, waist);
- *unassigned triangle*: the set's triangle there has a corner that no ray assigned (the
  paper's occluded vertices, filled smoothly): `eval`'s "assigned triangles" leave these out;
- *another chart*: the inferred mesh's triangle lies in another UV chart than gt's;
- *inside shown*: the inferred mesh shows the side of its triangle that faces away from the
  camera (the garment's inside, seen through an opening) where gt shows its outside.

--picture writes the image where the error outside the assigned triangles weighs most: the
texcoords' material error (blue 0 -> red >= 20 mm, the body grey, pixels of unassigned
triangles magenta) and a 4x enlargement around them.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def _rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(values * values))) if values.size else float("nan")


def opening_distance(dataset) -> np.ndarray:
    """Per vertex, the distance on the rest garment (m) to the nearest vertex on an opening:
    a boundary edge of the mesh with seam copies joined (a seam's two sides are one edge)."""
    from scipy.spatial import cKDTree

    from mvtex.data.mesh import weld_groups

    rest = np.asarray(dataset.rest, np.float64)
    group = weld_groups(rest)
    f = group[np.asarray(dataset.faces, np.int64)]
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    unique, count = np.unique(edges, axis=0, return_counts=True)
    rim = np.unique(unique[count == 1])
    return cKDTree(rest[rim]).query(rest)[0]


def facing_away(positions: np.ndarray, faces: np.ndarray, camera) -> np.ndarray:
    """Per face, whether its outside (counter-clockwise side) faces away from the camera."""
    x = np.asarray(positions, np.float64)[np.asarray(faces, np.int64)]
    normal = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    return np.einsum("ij,ij->i", normal, np.asarray(camera.center, np.float64) - x.mean(axis=1)) < 0


def image_classes(errors, evaluator, dataset, k, camera, near: np.ndarray) -> dict[str, np.ndarray]:
    """The pixel classes of one `ImageErrors` (boolean arrays over `errors.pixels`)."""
    raster = errors.raster
    base_tri = raster.base_tri.ravel()[errors.pixels]
    sub_tri = raster.sub_tri.ravel()[errors.pixels]
    gt = np.asarray(dataset.gt[k], np.float64)
    inferred = evaluator.positions(np.asarray(dataset.inferred[k], np.float64))
    inside_g = facing_away(gt, evaluator.faces, camera)[base_tri]
    inside_i = facing_away(inferred, evaluator.sub_faces, camera)[sub_tri]
    return {"near an opening": near[evaluator.faces[base_tri]].any(axis=1),
            "unassigned triangle": ~errors.in_assigned,
            "another chart": errors.other_chart,
            "inside shown": inside_i & ~inside_g}


def picture(errors, camera) -> np.ndarray:
    """The texcoords' material error with the pixels of unassigned triangles, and an enlargement."""
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
    marked = full(errors.pixels[~errors.in_assigned], True, False)
    image[marked] = CHART_BOUNDARY_COLOR
    rows, cols = np.nonzero(marked)
    size = camera.height // 4
    r = c = 0
    if rows.size:  # centre the enlargement on the largest error among the marked pixels
        err = full(errors.pixels, errors.mat_t, np.nan)[rows, cols]
        top = int(np.nanargmax(err))
        r = int(np.clip(rows[top] - size // 2, 0, camera.height - size))
        c = int(np.clip(cols[top] - size // 2, 0, camera.width - size))
    zoom = cv2.resize(image[r:r + size, c:c + size], (camera.width, camera.height), interpolation=cv2.INTER_NEAREST)
    framed = image.copy()
    cv2.rectangle(framed, (c, r), (c + size - 1, r + size - 1), (255, 255, 255), 1)
    return side_by_side([framed, zoom], ["material error (blue 0, red >= 20 mm)",
                                         "4x; magenta: unassigned triangles, grey: body"])


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", type=Path, help="dataset directory (with a rest shape)")
    parser.add_argument("texcoords", type=Path, help="texcoord set")
    parser.add_argument("--rig", default="stereo", help="the texcoord set's rig (default stereo)")
    parser.add_argument("--poses", help="pose SPEC (default the texcoord set's poses)")
    parser.add_argument("--picture", type=Path, help="write the picture of the image they weigh most in")
    parser.add_argument("--near-opening", type=float, default=0.03,
                        help="distance on the rest garment (m) that counts as near an opening (default 0.03)")
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
    near = opening_distance(ds) <= args.near_opening
    pooled: dict[str, list] = {"error_t": [], "error_b": []}
    worst = None
    with GLContext() as ctx:
        evaluator = ImageEvaluator(ctx, ds, tc.faces, tc.uv, tc.parent)
        for k in poses:
            for cam in cameras:
                errors = evaluator(k, cam, tc.texcoords(cam.name, k), assigned=tc.assigned(cam.name, k))
                pooled["error_t"].append(errors.mat_t)
                pooled["error_b"].append(errors.mat_b)
                for name, mask in image_classes(errors, evaluator, ds, k, cam, near).items():
                    pooled.setdefault(name, []).append(mask)
                outside = errors.mat_t[~errors.in_assigned]
                weight = float(np.sum(outside * outside))
                if worst is None or weight > worst[0]:
                    worst = (weight, k, cam, errors)
    error_t = np.concatenate(pooled.pop("error_t"))
    error_b = np.concatenate(pooled.pop("error_b"))
    classes = {name: np.concatenate(masks) for name, masks in pooled.items()}
    squared = error_t * error_t
    print(f"{len(error_t)} pixels in {len(poses) * len(cameras)} images of {args.texcoords} ({args.rig}); "
          f"material error of the texcoords {1e3 * np.sqrt(squared.mean()):.2f} mm RMS over all pixels, "
          f"of the baseline {1e3 * np.sqrt(np.mean(error_b ** 2)):.2f} mm\n")
    print("| pixels | share of pixels | share of the squared error | median error (mm) | RMS error (mm) |\n"
          "|---|---:|---:|---:|---:|")
    table = {}
    for name, mask in {**classes, "near an opening, unassigned triangle":
                       classes["near an opening"] & classes["unassigned triangle"]}.items():
        row = {"pixel_share": float(mask.mean()), "error_share": float(squared[mask].sum() / squared.sum()),
               "median_mm": float(1e3 * np.median(error_t[mask])) if mask.any() else float("nan"),
               "rms_mm": float(1e3 * np.sqrt(squared[mask].mean())) if mask.any() else float("nan")}
        table[name] = row
        print(f"| {name} | {100 * row['pixel_share']:.2f} % | {100 * row['error_share']:.1f} % | "
              f"{row['median_mm']:.1f} | {row['rms_mm']:.1f} |")
    if args.picture and worst is not None:
        _, k, cam, errors = worst
        save_png(args.picture, picture(errors, cam))
        print(f"\nwrote {args.picture}: pose {k}, camera {cam.name}")
    return {"pixels": int(len(error_t)), "classes": table}


if __name__ == "__main__":
    main()
