"""Picture of what the U-Net TSNN reads: the geometry images of one pose's inferred mesh,
the view of camera `left`, and the displacement target of texture sliding.

    python benchmarks/tsnn_geometry_images.py DATASET TEXCOORDS OUT.png [--pose K] [--resolution 64]

TEXCOORDS must hold camera `left` of the stereo rig and pose K (default: the first test
pose). Images are shown with v up (atlas row 0 at the bottom).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("texcoords", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--pose", type=int)
    parser.add_argument("--resolution", type=int, default=64)
    args = parser.parse_args()

    import torch
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from mvtex.data.dataset import load_dataset
    from mvtex.data.rig import builtin_rig_file, load_rig
    from mvtex.data.texcoords import open_texcoords
    from mvtex.tsnn.atlas import AtlasSampler
    from mvtex.tsnn.geometry import CHANNEL_NAMES, geometry_images
    from mvtex.tsnn.model import UNet

    ds = load_dataset(args.dataset)
    tc = open_texcoords(args.texcoords, ds.num_vertices)
    pose = ds.split["test"][0] if args.pose is None else args.pose
    sampler = AtlasSampler(tc.faces, tc.uv, args.resolution)
    geo = geometry_images(ds, [pose], sampler, tc.parent)
    cam = torch.tensor(load_rig(builtin_rig_file("stereo"))["left"].cam_from_world, dtype=torch.float32)[None]
    view = UNet.view_features(torch.from_numpy(geo), cam).numpy()
    target = sampler.to_image(tc.displacement("left", pose)).transpose(2, 0, 1)
    region = sampler.layout.tri_id >= 0
    panels = [(CHANNEL_NAMES[c], geo[0, c]) for c in range(geo.shape[1])]
    panels += [("depth (camera z)", view[0, 2]), ("facing: -cos(n, ray)", view[0, 6]),
               ("target d_u", target[0]), ("target d_v", target[1])]
    fig = Figure(figsize=(13, 6.2), dpi=90)
    FigureCanvasAgg(fig)
    for i, (name, image) in enumerate(panels):
        ax = fig.add_subplot(3, 5, i + 1)
        shown = np.where(region, image, np.nan)
        lo, hi = np.nanpercentile(shown, [2, 98])
        if name.startswith(("target", "strain", "curvature")):
            lo, hi = -max(abs(lo), abs(hi)), max(abs(lo), abs(hi))
        im = ax.imshow(shown, origin="lower", cmap="coolwarm", vmin=lo, vmax=hi)
        fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02)
        ax.set_title(name, fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle(f"U-Net TSNN inputs and target, pose {pose}, camera left, {args.resolution}² atlas "
                 "(front chart left, back chart right)", fontsize=10)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, format="png")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
