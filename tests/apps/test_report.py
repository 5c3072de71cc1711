"""The HTML report: GLB export read back by trimesh, and the page opened in headless
Chromium (skipped where Chromium or node's packages are missing; .ci/run installs them)."""

from __future__ import annotations

import numpy as np
import pytest
from browser import console_errors, open_pages

from mvtex.apps.report import (
    copy_viewer,
    figure,
    garments_frame,
    missing_images,
    model_view,
    page,
    scene_view,
    table,
    write_html,
)
from mvtex.formats.glb import export_glb


def test_glb_holds_the_meshes_side_by_side(tmp_path, sheet):
    import trimesh

    faces, uv, rest = sheet
    colors = (np.arange(len(rest))[:, None] * np.array([[1, 3, 7]]) % 256).astype(np.uint8)
    export_glb(tmp_path / "m.glb", [("a", rest, faces, colors), ("b", rest + 5.0, faces, colors)])
    scene = trimesh.load(tmp_path / "m.glb", force="scene")
    meshes = {name: geom for name, geom in scene.geometry.items()}
    assert set(meshes) == {"a", "b"}
    for mesh in meshes.values():
        assert len(mesh.vertices) == len(rest) and len(mesh.faces) == len(faces)
        assert np.array_equal(mesh.visual.vertex_colors[:, :3], colors)
    # Centred (world axes kept: y up, as glTF), placed apart along x.
    a = scene.dump(concatenate=False)
    xs = sorted(float(m.vertices[:, 0].mean()) for m in a)
    assert xs[1] - xs[0] == pytest.approx(1.25 * np.ptp(rest[:, 0]), rel=1e-6)
    assert np.allclose(meshes["a"].vertices[:, 1:], rest[:, 1:] - rest[:, 1:].mean(axis=0), atol=1e-6)


def test_glb_draws_the_body_inside_every_mesh(tmp_path, sheet):
    """The body moves with each mesh: its offset to the cloth is the world's in both."""
    import trimesh

    faces, uv, rest = sheet
    box = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    body = (np.asarray(box.vertices) + [0.0, 0.0, -0.2], np.asarray(box.faces), (168, 163, 156))
    colors = np.full((len(rest), 3), 200, np.uint8)
    export_glb(tmp_path / "m.glb", [("a", rest, faces, colors), ("b", rest + 5.0, faces, colors)], body=body)
    scene = trimesh.load(tmp_path / "m.glb", force="scene")
    meshes = dict(scene.geometry.items())
    assert set(meshes) == {"a", "b", "a_body", "b_body"}
    for name, cloth in (("a", rest), ("b", rest + 5.0)):
        offset = meshes[f"{name}_body"].vertices[0] - meshes[name].vertices[0]
        assert np.allclose(offset, body[0][0] - cloth[0], atol=1e-6)
        assert np.all(meshes[f"{name}_body"].visual.vertex_colors[:, :3] == (168, 163, 156))


def test_missing_images_finds_absent_files(tmp_path):
    (tmp_path / "there.png").write_bytes(b"x")
    text = '<img src="there.png"><img alt="" src="gone.png"><img src="data:image/png;base64,AA==">'
    assert missing_images(text, tmp_path) == ["gone.png"]


@pytest.mark.slow
def test_report_opens_in_headless_chromium(tmp_path, sheet, sheet_set, gl):
    """A page with a picture, the meshes' view and the scene viewer: every image loads, both
    3-D views are ready, the console holds no error; a missing picture is counted."""
    from mvtex.data.dataset import load_dataset
    from mvtex.util.files import save_png
    from mvtex.views.scene import ExportOptions, export_scene

    faces, uv, rest = sheet
    out = tmp_path / "report"
    out.mkdir()
    ramp = np.zeros((60, 90, 3), np.uint8)
    ramp[..., 0] = np.linspace(0, 255, 90)[None].astype(np.uint8)
    save_png(out / "pictures" / "ramp.png", ramp)
    meshes = [(name, rest + [0, 0, 0.01 * i], faces, np.full((len(rest), 3), 60 + 60 * i, np.uint8))
              for i, name in enumerate(["gt", "inferred", "reconstruction"])]
    glb = export_glb(out / "sheet.glb", meshes)
    data, rig_path, tc_path = sheet_set
    export_scene(load_dataset(data), tc_path, 2, out / "scene", rig=rig_path, options=ExportOptions(viewer=False))
    copy_viewer(out)
    html = page("test report", [("numbers", table(["a", "b"], [["x", 1.5]])),
                                ("picture", figure("pictures/ramp.png", "a ramp")),
                                ("3-D", model_view(glb, "the sheet", frame=garments_frame([m[1] for m in meshes]),
                                                   labels={"gt": "gt", "inferred": "inferred",
                                                           "reconstruction": "reconstruction"})),
                                ("scene", scene_view(out / "scene", out, "the scene"))], viewer=True)
    write_html(out / "report.html", html)
    assert missing_images(html, out) == [] and "model-viewer" not in html
    spec = {"url": (out / "report.html").as_uri(), "width": 1100, "height": 900}
    result = open_pages([spec], tmp_path)[0]
    assert console_errors(result) == [], result["console"]
    assert result["attributes"]["data-broken-images"] == "0"
    assert [v["data-viewer"] for v in result["attributes"]["viewers"]] == ["ready", "ready"]
    assert "camera=" not in result["url"]  # the report's scene viewer leaves the address alone
    # The check is real: a page with a missing picture is reported as such.
    (out / "pictures" / "ramp.png").unlink()
    result = open_pages([spec], tmp_path)[0]
    assert result["attributes"]["data-broken-images"] == "1"
