"""`mvtex render`: textured pictures of gt and inferred meshes per camera, and raster dumps.

Output layout (DESIGN §4):
    OUT/<camera>/gt.png, OUT/<camera>/inferred.png     textured renders
    OUT/<camera>/gt_shaded.png, inferred_shaded.png     untextured geometry under a key light
                                                        (folds show as light and shade)
    OUT/<camera>/shaded_zoom.png                        gt | inferred shaded, zoomed on the garment
    OUT/<camera>/gt_raster.npz, inferred_raster.npz     with raster=True: tri_id, bary, depth, uv
                                                        (and body, for a dataset with a body)
    OUT/overview.png                                    all cameras, gt above inferred
    OUT/render.json                                     the options that made it

An inference set (no gt) gives the inferred pictures alone: no gt column, and shaded_zoom.png
holds the inferred geometry only.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from tqdm import tqdm

from mvtex.data.camera import Camera
from mvtex.data.dataset import Dataset, as_dataset
from mvtex.data.rig import Rig, as_rig, check_outside_body, check_sees
from mvtex.data.texcoords import TexcoordSet, as_texcoords
from mvtex.render import raster as gl
from mvtex.render.context import GLContext
from mvtex.render.pictures import grid_image, side_by_side
from mvtex.render.shading import garment_box, render_shaded, render_textured, scaled_camera
from mvtex.util.checks import as_index, as_path
from mvtex.util.errors import InputError
from mvtex.util.files import read_row, save_png, write_json
from mvtex.util.output import atomic_path, writer

if TYPE_CHECKING:
    from mvtex.render.context import GLContext


@dataclass(frozen=True)
class MeshView:
    """What to draw for one camera: positions (n,3), faces (m,3), texcoords (n,2)."""

    positions: np.ndarray
    faces: np.ndarray
    texcoords: np.ndarray


def pose_views(dataset: Dataset, pose: int, camera: str,
               texcoord_set: TexcoordSet | None = None) -> dict[str, MeshView]:
    """The gt mesh (with T_G; none in an inference set) and the inferred mesh (with T_G, or the
    set's T_N on its mesh)."""
    views = {}
    if dataset.has_gt:
        views["gt"] = MeshView(np.asarray(dataset.gt[pose], np.float64), dataset.faces, dataset.uv)
    inferred_pos = np.asarray(dataset.inferred[pose], np.float64)
    if texcoord_set is None:
        views["inferred"] = MeshView(inferred_pos, dataset.faces, dataset.uv)
    else:
        views["inferred"] = MeshView(texcoord_set.positions(inferred_pos), texcoord_set.faces,
                                     texcoord_set.texcoords(camera, pose))
    return views


def check_sees_mesh(raster, camera: Camera, rig: Rig, pose: int, what: str) -> None:
    if not np.any(raster.tri_id >= 0):
        raise InputError(rig.source, f"camera {camera.name!r} sees nothing of the {what} mesh at pose {pose}")


@writer("render", inputs=lambda a: (a["dataset"], a["texcoord_set"], a["rig"]))
def render_pose(dataset: Dataset, rig: Rig, pose: int, out: str | os.PathLike, *,
                texcoord_set: TexcoordSet | None = None, raster: bool = False, progress: bool = True, ctx: GLContext | None = None, overwrite: bool = False) -> dict:
    """Render one pose from every camera of a rig into `out` (see module docstring); the
    dataset's body, if it has one, is drawn with the cloth (neutral matte) and is in the
    rasters' depth test.

    `out` is written whole under a temporary name and renamed into place, so a killed
    render leaves no half folder; the writer policy of `mvtex.util.output` applies.

    Args:
        ctx: the GL context (one is created, and released, for this call if None).
        overwrite: replace another command's output at `out` (never files mvtex did not
            write, never an input).

    Returns:
        {"pose": k, "cameras": [...], "files": [...]} (paths relative to out).
    """

    dataset = as_dataset(dataset)
    rig = as_rig(rig)
    texcoord_set = None if texcoord_set is None else as_texcoords(texcoord_set, "texcoord_set")
    pose = as_index(pose, "pose")
    out = as_path(out, "out")

    if not 0 <= pose < dataset.num_poses:
        raise InputError(dataset.path, f"pose {pose} out of range (dataset has {dataset.num_poses} poses)")
    for cam in rig:
        cam.require_pinhole(rig.source)
    if texcoord_set is not None:
        texcoord_set.check_dataset(dataset)
        texcoord_set.check_rig(rig, cameras=rig.names)
    check_sees(rig, read_row(dataset.inferred, pose), what=f"the inferred mesh of {dataset.path} at pose {pose}")
    check_outside_body(rig, dataset, [pose])
    if ctx is None:
        with GLContext() as own:
            return render_pose(dataset, rig, pose, out, texcoord_set=texcoord_set, raster=raster,
                               progress=progress, ctx=own)
    with atomic_path(out) as tmp:
        tmp.mkdir()
        return _render_into(tmp, dataset, rig, pose, texcoord_set, raster, progress, ctx)


def _render_into(out: Path, dataset: Dataset, rig: Rig, pose: int, texcoord_set: TexcoordSet | None, raster: bool,
                 progress: bool, ctx: GLContext) -> dict:

    files, tiles = [], []
    body = None if dataset.body is None else (dataset.body.pose(pose), dataset.body.faces)
    for cam in tqdm(list(rig), desc=f"render pose {pose}", unit="camera", disable=not progress):
        views = pose_views(dataset, pose, cam.name, texcoord_set)
        row, zooms = [], []
        framed = views["gt"] if "gt" in views else views["inferred"]
        zoom_cam = scaled_camera(cam, garment_box(framed.positions, cam), cam.width, cam.height)
        for what, view in views.items():
            r = gl.rasterize(ctx, view.positions, view.faces, cam, occluder=body)
            check_sees_mesh(r, cam, rig, pose, what)
            image = render_textured(ctx, view.positions, view.faces, view.texcoords, cam, body=body)
            save_png(out / cam.name / f"{what}.png", image)
            files.append(f"{cam.name}/{what}.png")
            row.append(image)
            save_png(out / cam.name / f"{what}_shaded.png", render_shaded(ctx, view.positions, view.faces, cam, body=body))
            files.append(f"{cam.name}/{what}_shaded.png")
            zooms.append(render_shaded(ctx, view.positions, view.faces, zoom_cam, body=body))
            if raster:
                uv = gl.interpolate(view.texcoords, r, view.faces)
                arrays = dict(tri_id=r.tri_id, bary=r.bary, depth=r.depth, uv=uv)
                if body is not None:
                    arrays["body"] = r.body
                with atomic_path(out / cam.name / f"{what}_raster.npz") as tmp:
                    with open(tmp, "wb") as f:
                        np.savez_compressed(f, **arrays)
                files.append(f"{cam.name}/{what}_raster.npz")
        save_png(out / cam.name / "shaded_zoom.png", side_by_side(zooms, list(views)))
        files.append(f"{cam.name}/shaded_zoom.png")
        tiles.append(row + zooms)

    shown = ["gt", "inferred"] if dataset.has_gt else ["inferred"]
    labels = shown + [f"{what} geometry, zoom" for what in shown]
    save_png(out / "overview.png", grid_image([[t[i] for t in tiles] for i in range(len(labels))],
                                              col_labels=rig.names, row_labels=labels))
    files.append("overview.png")
    summary = {"pose": int(pose), "cameras": rig.names, "dataset": str(dataset.path), "ground_truth": dataset.has_gt,
               "texcoords": None if texcoord_set is None else str(texcoord_set.path), "raster": bool(raster),
               "files": files}
    write_json(out / "render.json", summary)
    return summary
