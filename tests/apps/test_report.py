"""The HTML report: GLB export read back by trimesh, and the page opened in headless
Chromium (skipped where Chromium is not installed; .ci/run installs it when apt can)."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess

import numpy as np
import pytest

from mvtex.apps.report import copy_viewer, figure, missing_images, model_view, page, table, write_html
from mvtex.formats.glb import export_glb

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def chromium(*args, user_data_dir):
    """Headless Chromium with no network chatter and no GPU; returns stdout."""
    cmd = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
           "--disable-background-networking", "--disable-component-update", "--disable-sync",
           f"--user-data-dir={user_data_dir}", "--virtual-time-budget=8000", *map(str, args)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                            start_new_session=True)
    try:
        return proc.communicate(timeout=180)[0]
    except subprocess.TimeoutExpired:  # a starved machine, not a broken page
        os.killpg(proc.pid, signal.SIGKILL)  # chromium's helper processes too
        proc.communicate()
        pytest.skip("chromium did not finish within 180 s")


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


@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed")
def test_report_opens_in_headless_chromium(tmp_path, sheet, gl):
    from mvtex.util.files import save_png

    faces, uv, rest = sheet
    out = tmp_path / "report"
    out.mkdir()
    ramp = np.zeros((60, 90, 3), np.uint8)
    ramp[..., 0] = np.linspace(0, 255, 90)[None].astype(np.uint8)
    save_png(out / "pictures" / "ramp.png", ramp)
    glb = export_glb(out / "sheet.glb", [("sheet", rest, faces, np.full((len(rest), 3), 200, np.uint8))])
    copy_viewer(out)
    html = page("test report", [("numbers", table(["a", "b"], [["x", 1.5]])),
                                ("picture", figure("pictures/ramp.png", "a ramp")),
                                ("3-D", model_view(glb, "the sheet"))], viewer=True)
    write_html(out / "report.html", html)
    assert missing_images(html, out) == []
    dom = chromium("--dump-dom", (out / "report.html").as_uri(), user_data_dir=tmp_path / "profile")
    assert re.search(r'data-broken-images="0"', dom), dom[:500]
    assert 'data-viewer="ready"' in dom
    assert missing_images(dom, out) == []
    # The check is real: a page with a missing picture is reported as such.
    (out / "pictures" / "ramp.png").unlink()
    dom = chromium("--dump-dom", (out / "report.html").as_uri(), user_data_dir=tmp_path / "profile")
    assert 'data-broken-images="1"' in dom
