"""Writing a reconstruction: the directory `mvtex triangulate --out` produces.

    reconstruction.ply          gt connectivity, uv as s/t, error-heatmap colours, uchar `triangulated`
    colmap/{cameras,images,points3D,rigs,frames}.bin
                                one COLMAP image per camera, one 3-D point per triangulated vertex
    images/<camera>.png         the inferred mesh textured with that camera's T_N
    comparison.png              gt / inferred / reconstruction (texture, shaded geometry, strain, error)
    comparison.json             its camera and colour scales (`pictures.comparison_scales`)
    report.json                 `mvtex.recon.report.reconstruction_report`

The directory is written under a temporary name and renamed when complete. Formats are
delegated: PLY to `mvtex.formats.ply`, COLMAP to `mvtex.formats.colmap`, pictures to `mvtex.render.pictures`.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import TYPE_CHECKING, Iterator

import numpy as np
from tqdm import tqdm

from mvtex.data.rig import Rig
from mvtex.formats.colmap import point_reconstruction, track_tables
from mvtex.formats.ply import write_ply
from mvtex.recon.triangulate import ReconOptions, Reconstruction
from mvtex.render.context import context_or_new
from mvtex.render.pictures import comparison_picture, comparison_scales, error_colors, texture_colors
from mvtex.render.shading import render_textured
from mvtex.util.files import save_png, write_json
from mvtex.util.output import atomic_path

if TYPE_CHECKING:
    from mvtex.render.context import GLContext


@contextlib.contextmanager
def _atomic_dir(path: Path) -> Iterator[Path]:
    """`io.atomic_path` for a directory: yields the created temporary directory."""

    with atomic_path(path) as tmp:
        tmp.mkdir()
        yield tmp


def export_reconstruction(out: str | os.PathLike, rec: Reconstruction, rig: Rig, *, faces: np.ndarray,
                          uv: np.ndarray, gt: np.ndarray | None, rest: np.ndarray | None,
                          inferred_mesh: tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]] | None,
                          report: dict, options: ReconOptions = ReconOptions(), progress: bool = False,
                          ctx: GLContext | None = None, body: tuple[np.ndarray, np.ndarray] | None = None) -> Path:
    """Write a reconstruction directory atomically (layout in the module docstring).

    Args:
        out: the directory to write.
        rec: the reconstruction; rig: its cameras (observations keyed by their names).
        faces: (m,3) int gt mesh connectivity; uv: (n,2) T_G.
        gt: (n,3) gt positions for the error colours and the comparison picture (None: grey
            vertices, no comparison.png).
        rest: (n,3) rest shape for the strain row of the comparison, or None.
        inferred_mesh: (X_N' (n',3), faces' (m',3), {camera: T_N (n',2)}) for images/<camera>.png,
            or None (no images/).
        report: written as report.json.
        options: error_scale_m colours the PLY.
        progress: progress bar over the images on stderr.
        ctx: the GL context (`mvtex.render.context.GLContext`); one is made when None.
        body: optional (positions (nb,3), faces (mb,3)) of the wearer, drawn in the pictures.

    Returns:
        The directory written.
    """

    out = Path(out)
    names = [c for c in rig.names if c in rec.observations]
    tri_idx = np.flatnonzero(rec.triangulated)
    with _atomic_dir(out) as tmp, context_or_new(ctx) as ctx:
        if gt is not None:
            colors = error_colors(np.linalg.norm(rec.points - gt, axis=1), options.error_scale_m)
        else:
            colors = np.full((len(rec.points), 3), 180, np.uint8)
        write_ply(tmp / "reconstruction.ply", rec.points, faces, uv=uv, colors=colors,
                  vertex_properties={"triangulated": rec.triangulated.astype(np.uint8)},
                  comments=(f"mvtex reconstruction, pose {report.get('pose')}",
                            f"colour: |reconstructed - gt| blue 0 .. red >= {options.error_scale_m} m"
                            if gt is not None else "colour: grey (no ground truth to compare with)"))

        pixels = np.stack([rec.observations[name][tri_idx] for name in names], axis=1)
        observations, tracks = track_tables(names, pixels, np.isfinite(pixels[..., 0]))
        model, _ = point_reconstruction(rig.select(names), observations, rec.points[tri_idx], tracks,
                                        texture_colors(np.asarray(uv)[tri_idx]))
        (tmp / "colmap").mkdir()
        model.write_binary(str(tmp / "colmap"))

        # Images of the texture-corrected inferred mesh, so COLMAP's GUI shows the model on them.
        if inferred_mesh is not None:
            X_sub, faces_sub, T = inferred_mesh
            (tmp / "images").mkdir()
            for name in tqdm(names, desc="images", unit="camera", disable=not progress, leave=False):
                picture = render_textured(ctx, X_sub, faces_sub, T[name], rig[name], body=body)
                save_png(tmp / "images" / f"{name}.png", picture)
        if gt is not None:
            views = np.array([np.isfinite(rec.observations[c][:, 0]).sum() for c in names])
            camera = rig[names[int(np.argmax(views))]]
            scales = comparison_scales(faces, gt, rec.inferred, rec.points, rest)
            save_png(tmp / "comparison.png",
                     comparison_picture(camera, faces, uv, gt, rec.inferred, rec.points, rest, scales=scales,
                                        triangulated=rec.triangulated, ctx=ctx, body=body))
            write_json(tmp / "comparison.json", {"camera": camera.name,
                                                 "scales": {k: v.to_json() for k, v in scales.items()}})
        write_json(tmp / "report.json", report)
    return out
