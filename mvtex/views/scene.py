"""`mvtex export`: one pose as a glTF scene with every camera's texture coordinates, and a
page that blends them as you turn the view (the paper's AR/VR application, in a browser or an
engine).

Output (OUT, written whole or not at all):
    scene.glb     glTF 2.0 (`mvtex.formats.glb.scene_glb`): the node "cloth", the inferred mesh
                  of the pose (the texcoord set's mesh: subdivided if the set is) with the
                  fabric texture, TEXCOORD_0 = T_G and TEXCOORD_k = T_G + d of the set's k-th
                  camera (in the rig's order); the node "body" (the dataset's body, grey); one
                  camera node per camera, its extras.mvtex naming its texcoord set and holding
                  its K and image size; the scene's extras.mvtex describing all of it.
    viewer.html   the scene in three.js, offline (scripts and scene inside the page): drag to
                  turn, scroll to zoom; the texture coordinates are the cameras' blended with
                  the weights `mvtex preview` gives the eye's position (`weights_for_centre`),
                  so that at a camera's own viewpoint it shows that camera's texture sliding.
                  URL parameters (view, camera, texcoords, body, stereo, ipd): docs/views.md.
    export.json   what was exported (`SceneExport.to_json()`).

Positions stay in the dataset's world frame (meters): glTF's +Y up matches the built-in data,
whose cameras look from +Z; other data keeps its own axes, cameras and mesh together.
"""

from __future__ import annotations

import base64
import html
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from mvtex.data.dataset import as_dataset
from mvtex.data.mesh import vertex_normals, weld_groups
from mvtex.data.rig import Rig, as_rig
from mvtex.data.texcoords import as_texcoords, recorded_rig
from mvtex.formats.glb import SceneCamera, scene_glb
from mvtex.render.shading import BODY_RGB, fabric_texture
from mvtex.util.checks import as_index, as_path, check_instance
from mvtex.util.errors import InputError
from mvtex.util.files import read_row, write_json
from mvtex.util.output import atomic_path, writer
from mvtex.views.options import ExportOptions

SCENE_FORMAT = "mvtex-scene"
# The page's scripts, in load order: three.js (vendored, with its controls and glTF loader),
# then mvtex's own.
SCRIPTS = (("vendor", "three.min.js"), ("web", "viewmath.js"), ("web", "viewer.js"))


@dataclass(frozen=True)
class SceneExport:
    """What `export_scene` wrote.

    Attributes:
        out: the output folder. pose: the dataset pose. cameras: the camera of each texcoord
        set TEXCOORD_1 ... (TEXCOORD_0 is T_G). num_vertices, num_faces: the cloth mesh's.
        body: whether the scene has the body. files: what OUT holds.
    """

    out: Path
    pose: int
    cameras: list[str]
    num_vertices: int
    num_faces: int
    body: bool
    source: str
    options: ExportOptions
    files: list[str]

    def to_json(self) -> dict:
        return {"out": str(self.out), "pose": self.pose, "cameras": self.cameras,
                "texcoords": {"TEXCOORD_0": "T_G", **{f"TEXCOORD_{k}": c for k, c in enumerate(self.cameras, 1)}},
                "num_vertices": self.num_vertices, "num_faces": self.num_faces, "body": self.body,
                "source": self.source, "options": asdict(self.options), "files": self.files}


def script_path(folder: str, name: str) -> Path:
    """A script shipped with mvtex (`SCRIPTS`): mvtex/vendor/ or mvtex/web/."""
    return Path(__file__).resolve().parents[1] / folder / name


@writer("export", inputs=lambda a: (a["dataset"], a["texcoords"], a["rig"]))
def export_scene(dataset, texcoords, pose: int, out: str | os.PathLike, *, rig: Rig | str | os.PathLike | None = None,
                 options: ExportOptions = ExportOptions(), overwrite: bool = False) -> SceneExport:
    """`mvtex export`: OUT/scene.glb and OUT/viewer.html of one pose (see the module docstring).

    Reads no ground truth: a set predicted for an inference set exports as one slid from gt.

    Args:
        dataset: `Dataset` or its folder. texcoords: `TexcoordSet` or its folder.
        pose: dataset pose index (one of the set's poses).
        out: output folder (the writer policy of `mvtex.util.output`: an earlier export is
            replaced, never files mvtex did not write, never an input).
        rig: the cameras (a `Rig`, a rig file or a built-in rig's name); default the rig the
            texcoord set records (TC/rig.yaml).
        options: ExportOptions.

    Returns:
        A `SceneExport`; `.to_json()` is export.json (and `mvtex export --json`).
    """

    dataset = as_dataset(dataset)
    texcoords = as_texcoords(texcoords)
    pose = as_index(pose, "pose")
    out = as_path(out, "out")
    check_instance(options, ExportOptions, "options")
    if rig is None:
        rig = recorded_rig(texcoords.path)
        if rig is None:
            raise InputError(texcoords.path, "records no rig (rig.yaml): give the cameras (rig=... or --rig)")
    rig = as_rig(rig)
    if not 0 <= pose < dataset.num_poses:
        raise InputError(dataset.path, f"pose {pose} is outside [0, {dataset.num_poses})")
    texcoords.row(pose)  # InputError for a pose the set does not have
    texcoords.check_dataset(dataset)
    texcoords.check_rig(rig)
    names = [c for c in rig.names if c in texcoords.cameras]
    for name in names:
        rig[name].require_pinhole(rig.source)
    inferred = read_row(dataset.inferred, pose).astype(np.float64)
    positions = texcoords.positions(inferred)
    faces = np.asarray(texcoords.faces, np.int64)
    sets = [texcoords.uv.astype(np.float64)] + [texcoords.texcoords(c, pose).astype(np.float64) for c in names]
    body = None
    if dataset.body is not None:
        b = dataset.body.pose(pose)
        body = (b, dataset.body.faces, vertex_normals(b, dataset.body.faces, weld_groups(b)), BODY_RGB)
    cameras = [SceneCamera(name=c, width=rig[c].width, height=rig[c].height, K=rig[c].K, R=rig[c].R, t=rig[c].t,
                           texcoord=k) for k, c in enumerate(names, 1)]
    extras = {"format": SCENE_FORMAT, "version": 1, "dataset": dataset.name, "pose": pose, "units": "m",
              "texcoords": {"source": texcoords.source, "subdiv": texcoords.subdiv},
              "attributes": {"TEXCOORD_0": "T_G", **{f"TEXCOORD_{k}": c for k, c in enumerate(names, 1)}},
              "cameras": names, "body": body is not None, "body_rgb": list(BODY_RGB),
              "conventions": "each camera node's extras.mvtex.K is OpenCV's: pixel (u, v), u right, v down, the "
                             "top-left pixel's centre at (0, 0); the node looks down its -Z with +Y up (glTF)"}
    files = ["scene.glb"] + (["viewer.html"] if options.viewer else []) + ["export.json"]
    result = SceneExport(out=out, pose=pose, cameras=names, num_vertices=len(positions), num_faces=len(faces),
                         body=body is not None, source=texcoords.source, options=options, files=files)
    normals = vertex_normals(positions, faces, weld_groups(positions))
    with atomic_path(out) as tmp:
        tmp.mkdir()
        glb = scene_glb(tmp / "scene.glb", positions=positions, faces=faces, normals=normals, texcoords=sets,
                        texture=fabric_texture(options.texture_size), cameras=cameras, body=body, extras=extras)
        if options.viewer:
            title = f"mvtex: {dataset.name}, pose {pose}, {len(names)} camera{'s' * (len(names) != 1)}"
            write_viewer_page(tmp / "viewer.html", glb, title)
        write_json(tmp / "export.json", result.to_json())
    return result


def glb_element(glb: Path, element_id: str) -> str:
    """A GLB as a base64 data block of a page, for the viewer to read (browsers refuse `fetch` from
    file://)."""
    data = base64.b64encode(Path(glb).read_bytes()).decode("ascii")
    return f'<script type="application/octet-stream" id="{html.escape(element_id)}">{data}</script>'


def inline_scripts() -> str:
    """`SCRIPTS` inside <script> elements (classic scripts: they run from file://)."""
    parts = []
    for folder, name in SCRIPTS:
        text = script_path(folder, name).read_text(encoding="utf-8").replace("</script", "<\\/script")
        parts.append(f"<script>/* {folder}/{name} */\n{text}\n</script>")
    return "\n".join(parts)


def write_viewer_page(path: Path, glb: Path, title: str) -> Path:
    """viewer.html: the scene viewer filling the window, everything inside the page."""

    text = (f'<!DOCTYPE html><html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>'
            '<meta name="viewport" content="width=device-width,initial-scale=1">'
            '<style>html,body{margin:0;height:100%;background:#28282e}#viewer{height:100vh}</style>'
            f'{inline_scripts()}</head><body><div id="viewer"></div>{glb_element(glb, "scene")}'
            '<script>mvtexViewer.openScene(document.getElementById("viewer"), '
            'document.getElementById("scene").textContent);</script></body></html>\n')
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return path
