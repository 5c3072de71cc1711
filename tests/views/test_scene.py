"""`mvtex export`: the glTF scene read back by an independent GLB reader and checked against
the texcoord set and OpenCV's projection; the Khronos validator on the built-in T-shirt with
every built-in rig; the viewer in headless Chromium against `mvtex render` of
`mvtex views --method blend` at the same camera."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
from browser import console_errors, open_pages, validate_gltf
from helpers import one_line_error, run, run_json

from mvtex.data.rig import load_rig
from mvtex.data.texcoords import open_texcoords
from mvtex.views.scene import ExportOptions, export_scene

COMPONENTS = {5126: np.float32, 5125: np.uint32, 5123: np.uint16, 5121: np.uint8}
SIZES = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}


def read_glb(path) -> tuple[dict, bytes]:
    """A GLB's JSON and binary chunks, by the container's layout (glTF 2.0 §4.4)."""
    from pathlib import Path

    data = Path(path).read_bytes()
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    assert magic == b"glTF" and version == 2 and length == len(data)
    size, kind = struct.unpack_from("<I4s", data, 12)
    assert kind == b"JSON"
    tree = json.loads(data[20:20 + size])
    bsize, bkind = struct.unpack_from("<I4s", data, 20 + size)
    assert bkind == b"BIN\x00"
    return tree, data[28 + size:28 + size + bsize]


def accessor(tree: dict, blob: bytes, index: int) -> np.ndarray:
    acc = tree["accessors"][index]
    view = tree["bufferViews"][acc["bufferView"]]
    dtype = COMPONENTS[acc["componentType"]]
    width = SIZES[acc["type"]]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    stride = view.get("byteStride", np.dtype(dtype).itemsize * width)
    rows = [np.frombuffer(blob, dtype, width, start + i * stride) for i in range(acc["count"])] \
        if stride != np.dtype(dtype).itemsize * width else \
        [np.frombuffer(blob, dtype, acc["count"] * width, start).reshape(-1, width)]
    return np.vstack(rows) if len(rows) > 1 else rows[0].reshape(acc["count"], width)


def test_the_scene_holds_the_mesh_every_cameras_texcoords_and_the_cameras(tmp_path, sheet_set):
    import cv2

    from mvtex.data.dataset import load_dataset

    data, rig_path, tc_path = sheet_set
    dataset, tc, rig = load_dataset(data), open_texcoords(tc_path), load_rig(rig_path)
    result = export_scene(dataset, tc, 2, tmp_path / "scene", rig=rig, options=ExportOptions(viewer=False))
    assert sorted(p.name for p in (tmp_path / "scene").iterdir() if not p.name.startswith(".")) == \
        ["export.json", "scene.glb"]
    tree, blob = read_glb(tmp_path / "scene" / "scene.glb")
    nodes = {n["name"]: n for n in tree["nodes"]}
    cloth = tree["meshes"][nodes["cloth"]["mesh"]]["primitives"][0]
    attr = cloth["attributes"]
    assert set(attr) == {"POSITION", "NORMAL", "TEXCOORD_0", "TEXCOORD_1", "TEXCOORD_2"}
    # The set's (subdivided) inferred mesh of the pose, in world coordinates.
    expected = tc.positions(np.asarray(dataset.inferred[2], np.float64))
    assert np.allclose(accessor(tree, blob, attr["POSITION"]), expected, atol=1e-6)
    faces = accessor(tree, blob, cloth["indices"]).reshape(-1, 3)
    assert np.array_equal(faces, tc.faces)
    # glTF texcoords are (u, 1 - v) of mvtex's; TEXCOORD_k is the k-th camera's T_G + d.
    def texcoords(k):
        t = accessor(tree, blob, attr[f"TEXCOORD_{k}"]).astype(np.float64)
        return np.stack([t[:, 0], 1.0 - t[:, 1]], axis=1)

    assert np.allclose(texcoords(0), tc.uv, atol=1e-6)
    info = tree["scenes"][0]["extras"]["mvtex"]
    assert info["attributes"] == {"TEXCOORD_0": "T_G", "TEXCOORD_1": "a", "TEXCOORD_2": "b"}
    assert result.cameras == ["a", "b"] and info["pose"] == 2
    for k, name in enumerate(["a", "b"], 1):
        assert np.allclose(texcoords(k), tc.uv + tc.displacement(name, 2), atol=1e-6)
        assert not np.allclose(texcoords(k), tc.uv, atol=1e-4)  # the sliding is there
    # Camera nodes: the glTF camera (-Z forward, +Y up) at the node's pose with the extras' K
    # projects points where OpenCV projects them with the rig's camera.
    points = expected[::37]
    for name in ("a", "b"):
        node = nodes[name]
        ex = node["extras"]["mvtex"]
        assert ex["camera"] == name and tree["meshes"] and ex["attribute"] == f"TEXCOORD_{ex['texcoord']}"
        world_from_gl = np.asarray(node["matrix"], np.float64).reshape(4, 4).T
        gl = (np.linalg.inv(world_from_gl) @ np.c_[points, np.ones(len(points))].T)[:3].T
        K = np.asarray(ex["K"])
        x, y, z = gl[:, 0], -gl[:, 1], -gl[:, 2]  # OpenCV axes from glTF's camera axes
        pixels = np.stack([K[0, 0] * x / z + K[0, 2], K[1, 1] * y / z + K[1, 2]], axis=1)
        cam = rig[name]
        def f64(a):
            return np.ascontiguousarray(a, np.float64)

        reference, _ = cv2.projectPoints(f64(points), cv2.Rodrigues(f64(cam.R))[0], f64(cam.t), f64(cam.K), np.zeros(5))
        assert np.abs(pixels - reference.reshape(-1, 2)).max() < 1e-6
        persp = tree["cameras"][node["camera"]]["perspective"]
        assert persp["yfov"] == pytest.approx(2 * np.arctan(cam.height / (2 * cam.K[1, 1])))
        assert persp["aspectRatio"] == pytest.approx(cam.width / cam.height * cam.K[1, 1] / cam.K[0, 0])
    # The texture: the fabric, rows flipped as glTF's v runs down.
    import io

    from PIL import Image

    from mvtex.render.shading import fabric_texture

    material = tree["materials"][cloth["material"]]
    image = tree["images"][tree["textures"][material["pbrMetallicRoughness"]["baseColorTexture"]["index"]]["source"]]
    view = tree["bufferViews"][image["bufferView"]]
    png = blob[view.get("byteOffset", 0):view.get("byteOffset", 0) + view["byteLength"]]
    assert np.array_equal(np.asarray(Image.open(io.BytesIO(png)).convert("RGB")), fabric_texture(1024)[::-1])


def test_export_command_and_its_bad_inputs(capsys, tmp_path, sheet_set):
    data, rig_path, tc_path = sheet_set
    result = run_json(capsys, "export", data, "--texcoords", tc_path, "--rig", rig_path, "--pose", 4,
                      "--out", tmp_path / "e")
    assert result["cameras"] == ["a", "b"] and result["files"] == ["scene.glb", "viewer.html", "export.json"]
    page = (tmp_path / "e" / "viewer.html").read_text()
    assert "mvtexViewer.openScene" in page and 'src="' not in page  # everything inside the page
    # The set's recorded rig is the default; a set that records none needs --rig.
    assert run_json(capsys, "export", data, "--texcoords", tc_path, "--pose", 4, "--out", tmp_path / "f")["cameras"] \
        == ["a", "b"]
    import shutil

    shutil.copytree(tc_path, tmp_path / "bare", ignore=shutil.ignore_patterns("rig.yaml", ".mvtex*"))
    code, _, err = run(capsys, "export", data, "--texcoords", tmp_path / "bare", "--pose", 4, "--out", tmp_path / "f2")
    one_line_error(code, err, "--rig")
    code, _, err = run(capsys, "export", data, "--texcoords", tc_path, "--rig", rig_path, "--pose", 1,
                       "--out", tmp_path / "g")
    one_line_error(code, err, "pose 1 is not in this texcoord set")
    assert not (tmp_path / "g").exists()
    code, _, err = run(capsys, "export", data, "--texcoords", tc_path, "--rig", "square4", "--pose", 4,
                       "--out", tmp_path / "h")
    one_line_error(code, err, "not in the rig")
    code, _, err = run(capsys, "export", data, "--texcoords", tc_path, "--rig", rig_path, "--pose", 4,
                       "--texture-size", 100000, "--out", tmp_path / "i")
    one_line_error(code, err, "texture")
    # Never into a folder of someone else's files.
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep")
    code, _, err = run(capsys, "export", data, "--texcoords", tc_path, "--rig", rig_path, "--pose", 4,
                       "--out", tmp_path / "mine", "--overwrite")
    assert code == 2 and (tmp_path / "mine" / "notes.txt").read_text() == "keep"
    # A second export replaces the first (mvtex wrote it).
    run_json(capsys, "export", data, "--texcoords", tc_path, "--rig", rig_path, "--pose", 2, "--out", tmp_path / "e",
             "--overwrite")
    assert json.loads((tmp_path / "e" / "export.json").read_text())["pose"] == 2


@pytest.fixture(scope="module")
def shirt_scenes(tmp_path_factory, gl):
    """The built-in T-shirt (8 poses), its test pose slid from each built-in rig and exported:
    (folder, rig name -> scene folder, pose)."""
    from mvtex.data.dataset import load_dataset
    from mvtex.sliding.dataset import slide_dataset
    from mvtex.sliding.options import SlideOptions
    from mvtex.synth.generate import SynthOptions, write_synth

    root = tmp_path_factory.mktemp("shirt")
    write_synth(root / "shirt", SynthOptions(num_poses=8), progress=False)
    dataset = load_dataset(root / "shirt")
    pose = dataset.split["test"][0]  # the predictor was fitted to the others: they show little to slide
    scenes = {}
    for name in ("stereo", "square4", "trapezoid12"):
        slide_dataset(dataset, load_rig(name), root / f"ts_{name}", poses=[pose], options=SlideOptions(),
                      progress=False)
        export_scene(dataset, root / f"ts_{name}", pose, root / f"scene_{name}")
        scenes[name] = root / f"scene_{name}"
    return root, scenes, pose


@pytest.mark.slow
@pytest.mark.parametrize("rig", ["stereo", "square4", "trapezoid12"])
def test_the_khronos_validator_finds_no_error_and_no_warning(shirt_scenes, rig):
    report = validate_gltf(shirt_scenes[1][rig] / "scene.glb")
    issues = report["issues"]
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"][:10]
    cameras = len(load_rig(rig).names)
    assert report["info"]["totalVertexCount"] > 0
    tree, _ = read_glb(shirt_scenes[1][rig] / "scene.glb")
    assert len(tree["cameras"]) == cameras
    assert sum(k.startswith("TEXCOORD_") for k in tree["meshes"][0]["primitives"][0]["attributes"]) == cameras + 1


def _cloth_ssim(shot: np.ndarray, reference: np.ndarray, cloth: np.ndarray) -> float:
    """Mean SSIM (scikit-image, 7x7 windows) over the pixels where the reference shows cloth."""
    from skimage.metrics import structural_similarity

    _, full = structural_similarity(reference, shot, channel_axis=2, data_range=255, full=True)
    return float(full.mean(axis=2)[cloth].mean())


@pytest.mark.slow
def test_the_viewer_shows_what_views_blend_renders(capsys, tmp_path, shirt_scenes, gl):
    """Three eyes of square4: a camera's own viewpoint, the midpoint of two cameras and the
    centre of four; the page's screenshot against `mvtex render` of `mvtex views --method
    blend` at the camera the view parameter names, over the cloth's pixels."""
    import cv2

    from mvtex.data.dataset import load_dataset
    from mvtex.render.raster import rasterize
    from mvtex.views.cameras import interpolate_camera, weights_for_centre

    root, scenes, pose = shirt_scenes
    dataset = load_dataset(root / "shirt")
    rig = load_rig("square4")
    eyes = {"own": "tl=1", "midpoint": "tl=0.5,tr=0.5", "centre": "tl=0.25,tr=0.25,bl=0.25,br=0.25"}
    pages = [{"url": (scenes["square4"] / "viewer.html").as_uri() + f"?view={w}", "width": 512, "height": 556,
              "screenshot": str(tmp_path / f"{name}.png"), "element": "canvas"} for name, w in eyes.items()]
    results = open_pages(pages, tmp_path)
    body = (dataset.body.pose(pose), dataset.body.faces)
    scores = {}
    for (name, w), result in zip(eyes.items(), results):
        assert console_errors(result) == [] and result["attributes"]["data-viewer"] == "ready"
        weights = dict(item.split("=") for item in w.split(","))
        camera = interpolate_camera(rig, {k: float(v) for k, v in weights.items()}, name)
        # The page blends with the weights preview gives the eye: here the view's own.
        page_weights = json.loads(result["attributes"]["data-weights"])
        python_weights = weights_for_centre(rig, rig.names, camera.center)
        assert page_weights == pytest.approx(python_weights, abs=1e-7)
        assert {k: v for k, v in python_weights.items() if v > 1e-9} == pytest.approx(
            {k: float(v) for k, v in weights.items()}, abs=1e-9)
        code, _, err = run(capsys, "views", root / "shirt", "--rig", "square4", "--texcoords", root / "ts_square4",
                           "--poses", pose, "--method", "blend", "--weights", w, "--name", name,
                           "--out", tmp_path / f"views_{name}")
        assert code == 0, err
        code, _, err = run(capsys, "render", root / "shirt", "--texcoords", tmp_path / f"views_{name}", "--pose", pose,
                           "--out", tmp_path / f"render_{name}")
        assert code == 0, err
        reference = cv2.imread(str(tmp_path / f"render_{name}" / name / "inferred.png"))[..., ::-1]
        shot = cv2.imread(str(tmp_path / f"{name}.png"))[..., ::-1]
        assert shot.shape == reference.shape
        cloth = rasterize(gl, np.asarray(dataset.inferred[pose], np.float64), dataset.faces, camera, attributes=False,
                          occluder=body).mask
        scores[name] = _cloth_ssim(shot, reference, cloth)
        # The comparison can fail: the mesh's own T_G at the same eye is another picture.
        if name == "own":
            code, _, err = run(capsys, "render", root / "shirt", "--rig", "square4", "--cameras", "tl", "--pose", pose,
                               "--out", tmp_path / "render_tg")
            plain = cv2.imread(str(tmp_path / "render_tg" / "tl" / "inferred.png"))[..., ::-1]
            assert _cloth_ssim(plain, reference, cloth) < 0.8
    assert scores["own"] >= 0.98, scores
    assert scores["midpoint"] >= 0.95 and scores["centre"] >= 0.95, scores


@pytest.mark.slow
def test_the_viewer_turns_shares_its_view_and_toggles(tmp_path, shirt_scenes):
    """Dragging turns the view and the page's address then holds the camera: opening that
    address shows the same picture. The toggles change what is drawn."""
    import cv2

    scene = shirt_scenes[1]["stereo"] / "viewer.html"
    base = {"width": 512, "height": 556, "element": "canvas"}
    first = open_pages([{**base, "url": scene.as_uri() + "?view=left", "actions": [{"drag": [60, 20]}, {"wheel": -200}],
                         "screenshot": str(tmp_path / "turned.png")},
                        {**base, "url": scene.as_uri() + "?view=left", "screenshot": str(tmp_path / "left.png")},
                        {**base, "url": scene.as_uri() + "?view=left&texcoords=tg", "screenshot": str(tmp_path / "tg.png")},
                        {**base, "url": scene.as_uri() + "?view=left&body=0", "screenshot": str(tmp_path / "nobody.png")},
                        {**base, "width": 1024, "url": scene.as_uri() + "?view=left=0.5,right=0.5&stereo=1",
                         "screenshot": str(tmp_path / "stereo.png")},
                        {**base, "url": (shirt_scenes[1]["trapezoid12"] / "viewer.html").as_uri()
                         + "?view=cam06=0.5,cam07=0.5"}], tmp_path)
    for result in first:
        assert console_errors(result) == [] and result["attributes"]["data-viewer"] == "ready"
    twelve = json.loads(first[5]["attributes"]["data-weights"])  # 12 cameras, 13 texcoord sets
    assert len(twelve) == 12 and twelve["cam06"] == pytest.approx(0.5) and twelve["cam07"] == pytest.approx(0.5)
    turned_url = first[0]["url"]
    assert "camera=" in turned_url and "view=" not in turned_url
    again = open_pages([{**base, "url": turned_url, "screenshot": str(tmp_path / "again.png")}], tmp_path)[0]
    images = {p.stem: cv2.imread(str(p)).astype(np.int16) for p in tmp_path.glob("*.png")}
    assert np.abs(images["turned"] - images["left"]).mean() > 5  # the drag turned the view
    assert np.abs(images["again"] - images["turned"]).mean() < 0.5  # the address holds it
    assert json.loads(again["attributes"]["data-weights"]) == pytest.approx(
        json.loads(first[0]["attributes"]["data-weights"]), abs=1e-6)
    assert np.abs(images["tg"] - images["left"]).mean() > 1  # T_G is not the camera's sliding
    assert np.abs(images["nobody"] - images["left"]).mean() > 1
    assert images["stereo"].shape[1] == 2 * images["stereo"].shape[0]  # two eyes side by side
    left_eye, right_eye = images["stereo"][:, :512], images["stereo"][:, 512:]
    assert np.abs(left_eye - right_eye).mean() > 1
