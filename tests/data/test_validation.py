"""Input that must be refused where the object is built or loaded, through the command line
(`main(argv)`) and through the Python API: invalid cameras and rigs (a camera inside the
body, rotations that are not rotations, rigs the writer could write but the reader would
refuse), degenerate triangulation (one centre, one view, NaN pixels), non-finite or absurd
outputs (a broken model, `save_texcoords`), typed errors naming the argument, a
`--scheduler` that is not a Dask scheduler, and sizes bounded before memory is taken."""

from __future__ import annotations

import socket
import struct
import threading
import zlib
from pathlib import Path

import numpy as np
import pytest
from helpers import one_line_error, run, run_json

import mvtex
from mvtex.data.camera import look_at
from mvtex.data.rig import Rig, load_rig, save_rig


def _rotation(axis, angle) -> np.ndarray:
    """Rodrigues' formula (closed form, not mvtex's)."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])


# -- invalid cameras and rigs ------------------------------------------------------------------

@pytest.mark.parametrize("R, why", [
    (np.diag([1.0, 1.0, -1.0]), "a reflection (det -1)"),
    (1.001 * _rotation((0, 1, 0), 0.3), "a scaled rotation"),
    (_rotation((1, 2, 3), 0.7) + 1e-4 * np.arange(9).reshape(3, 3), "rows not orthonormal"),
    (np.zeros((3, 3)), "singular"),
])
def test_a_camera_refuses_a_matrix_that_is_not_a_rotation(R, why):
    with pytest.raises(mvtex.OptionError, match="R is not a rotation matrix"):
        mvtex.Camera("a", 640, 480, K, R, np.zeros(3))
    # A rotation to rounding (what a YAML rig stores) is accepted.
    mvtex.Camera("a", 640, 480, K, _rotation((1, 2, 3), 0.7) + 1e-12, np.zeros(3))


def test_look_at_names_the_argument_that_leaves_no_orientation():
    with pytest.raises(mvtex.OptionError, match="target must differ from center"):
        look_at("a", (0, 0, 1), (0, 0, 1), width=64, height=48, focal=50.0)
    with pytest.raises(mvtex.OptionError, match="up must not be parallel"):
        look_at("a", (0, 0, 0), (0, 3, 0), width=64, height=48, focal=50.0)
    with pytest.raises(mvtex.OptionError, match="focal"):
        look_at("a", (0, 0, 1), (0, 0, 0), width=64, height=48, focal=float("nan"))


@pytest.mark.parametrize("name", ["true", "false", "null", "True", "NULL", "1", "0", "1e3", "nan", "inf", "yes",
                                  "off", "a.b", "0x10", "-"])
def test_a_rig_that_saves_is_a_rig_that_loads(tmp_path, name):
    """save_rig and load_rig accept the same cameras: either both refuse a camera (saying
    so before anything is written) or the file reads back as the same rig."""
    try:
        camera = mvtex.Camera(name, 640, 480, K, _rotation((0, 1, 0), 0.2), np.array([0.1, 0, 1.5]))
    except mvtex.OptionError:
        return  # refused where the camera is made: neither writes nor reads it
    path = tmp_path / "rig.yaml"
    save_rig(Rig((camera,)), path)
    back = load_rig(path)
    assert back.names == [name]
    np.testing.assert_array_equal(back.cameras[0].R, camera.R)
    np.testing.assert_array_equal(back.cameras[0].K, camera.K)


def test_save_rig_refuses_what_is_no_rig(tmp_path):
    with pytest.raises(mvtex.OptionError, match="at least one camera"):
        save_rig(Rig(()), tmp_path / "rig.yaml")
    with pytest.raises(mvtex.OptionError, match="rig must be a Rig"):
        save_rig([look_at("a", (0, 0, 1), (0, 0, 0), width=8, height=8, focal=8.0)], tmp_path / "rig.yaml")
    assert not list(tmp_path.iterdir())


def test_views_refuses_a_view_name_a_rig_file_cannot_hold(tmp_path, capsys, tiny_dataset, slid_sheet):
    """A view named "true" would be written into the views' rig.yaml and could never be read."""
    out = tmp_path / "views"
    code, _, err = run(capsys, "views", tiny_dataset, "--rig", slid_sheet.parent / "rig.yaml", "--texcoords",
                       slid_sheet, "--weights", "a=0.5,b=0.5", "--name", "true", "--out", out)
    one_line_error(code, err, "true")
    assert not out.exists()


@pytest.fixture(scope="module")
def worn_sheet(tmp_path_factory, sheet):
    """The wavy sheet worn in front of a closed body: an icosphere 0.1 m behind it."""
    import trimesh
    from helpers import wave

    faces, uv, rest = sheet
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.1)
    body = np.repeat((ball.vertices + [0, 0, -0.3])[None], 3, axis=0).astype(np.float32)
    gt = np.stack([wave(rest, 0.015, p) for p in (0.0, 1.0, 2.0)])
    path = tmp_path_factory.mktemp("worn") / "sheet"
    mvtex.save_dataset(path, faces=faces, uv=uv, gt=gt, inferred=gt * [1, 1, 0.3], poses=np.eye(3),
                       rest=rest, body_faces=ball.faces, body=body)
    return path


def _inside_rig(tmp_path) -> Path:
    """Camera "a" in front of the sheet; camera "inside" at the body's centre, looking at the
    sheet (so it does see the sheet: only its place is wrong)."""
    rig = Rig((look_at("a", (0, 0.05, 1.2), (0, 0, 0), width=160, height=120, focal=260.0),
               look_at("inside", (0.01, 0.0, -0.3), (0, 0, 0), width=160, height=120, focal=100.0)))
    path = tmp_path / "rig.yaml"
    save_rig(rig, path)
    return path


def test_a_camera_inside_the_body_is_refused_by_the_library(tmp_path, worn_sheet):
    ds = mvtex.load_dataset(worn_sheet)
    rig = load_rig(_inside_rig(tmp_path))
    # Independent check of the premise: trimesh says the centre is inside the closed body.
    import trimesh

    ball = trimesh.Trimesh(ds.body.pose(1), ds.body.faces)
    assert ball.is_watertight and ball.contains([rig["inside"].center])[0]
    with pytest.raises(mvtex.InputError, match=r"camera 'inside' is inside the body .* at pose 1"):
        mvtex.slide_dataset(ds, rig, tmp_path / "ts", poses=[1], options=mvtex.SlideOptions(subdiv=0),
                            progress=False)
    assert not (tmp_path / "ts").exists() and not (tmp_path / "ts.partial").exists()
    # The camera outside the body alone is fine.
    from mvtex.data.rig import check_outside_body

    check_outside_body(rig.select(["a"]), ds, [0, 1, 2])


def test_a_camera_inside_the_body_is_refused_by_the_command_line(tmp_path, capsys, worn_sheet):
    out = tmp_path / "render"
    code, _, err = run(capsys, "render", worn_sheet, "--rig", _inside_rig(tmp_path), "--pose", 2, "--out", out)
    one_line_error(code, err, "rig.yaml", "'inside'", "pose 2")
    assert not out.exists()


# -- degenerate triangulation ------------------------------------------------------------------

@pytest.fixture(scope="module")
def cameras():
    a = look_at("a", (0, 0, 2), (0, 0, 0), width=640, height=480, focal=600.0)
    same_centre = look_at("b", (0, 0, 2), (0.3, 0.1, 0), width=640, height=480, focal=600.0)
    wide = look_at("c", (0.8, 0.1, 1.8), (0, 0, 0), width=640, height=480, focal=600.0)
    return a, same_centre, wide


def _pixels(cams, X):
    import cv2

    return np.stack([cv2.projectPoints(X, cv2.Rodrigues(c.R)[0], c.t, c.K, None)[0][:, 0] for c in cams], axis=1)


def test_cameras_at_one_centre_triangulate_no_point(cameras):
    a, b, c = cameras
    X = np.array([[0.05, 0.02, 0.0], [-0.1, 0.05, 0.1], [0.0, 0.0, -0.05]])
    noise = np.random.default_rng(0).normal(0, 0.2, (3, 2, 2))
    one_centre = mvtex.triangulate_points([a, b], _pixels([a, b], X) + noise, np.ones((3, 2)))
    assert np.isnan(one_centre).all()  # rays through one centre fix no depth
    wide = mvtex.triangulate_points([a, c], _pixels([a, c], X) + noise, np.ones((3, 2)))
    assert np.abs(wide - X).max() < 0.01  # a real baseline: a few mm at 0.2 px of noise
    # Three cameras, two of them at one centre: the third gives the baseline.
    three = mvtex.triangulate_points([a, b, c], _pixels([a, b, c], X), np.ones((3, 3)))
    np.testing.assert_allclose(three, X, atol=1e-6)


def test_one_view_or_a_nan_pixel_gives_no_point(cameras):
    a, _, c = cameras
    X = np.array([[0.05, 0.02, 0.0], [-0.1, 0.05, 0.1]])
    pixels = _pixels([a, c], X)
    assert np.isnan(mvtex.triangulate_points([a, c], pixels, np.array([[1.0, 0.0], [0.0, 1.0]]))).all()
    nan = pixels.copy()
    nan[0, 1] = np.nan
    out = mvtex.triangulate_points([a, c], nan, np.ones((2, 2)))
    assert np.isnan(out[0]).all()
    np.testing.assert_allclose(out[1], X[1], atol=1e-6)
    with pytest.raises(mvtex.OptionError, match="weights"):
        mvtex.triangulate_points([a, c], pixels, np.full((2, 2), np.nan))


@pytest.mark.slow
def test_the_command_line_triangulates_nothing_from_cameras_at_one_centre(tmp_path, capsys, tiny_dataset, gl):
    rig = Rig((look_at("a", (0, 0.05, 1.2), (0, 0, 0), width=160, height=120, focal=260.0),
               look_at("b", (0, 0.05, 1.2), (0.04, 0.02, 0), width=160, height=120, focal=260.0)))
    save_rig(rig, tmp_path / "rig.yaml")
    mvtex.slide_dataset(tiny_dataset, rig, tmp_path / "ts", poses=[1], options=mvtex.SlideOptions(subdiv=0),
                        progress=False, ctx=gl)
    result = run_json(capsys, "triangulate", tiny_dataset, "--rig", tmp_path / "rig.yaml", "--texcoords",
                      tmp_path / "ts", "--pose", 1, "--out", tmp_path / "recon")
    assert result["num_triangulated"] == 0


# -- non-finite or absurd outputs --------------------------------------------------------------

def _texcoord_arrays(slid):
    tc = mvtex.open_texcoords(slid)
    d = {c: np.stack([tc.displacement(c, p) for p in tc.poses]) for c in tc.cameras}
    a = {c: np.stack([tc.assigned(c, p) for p in tc.poses]) for c in tc.cameras}
    return tc, d, a


@pytest.mark.parametrize("damage, message", [
    (lambda d: d.__setitem__((0, 3, 1), np.nan), "NaN or infinite"),
    (lambda d: d.__setitem__((1, 0, 0), np.inf), "NaN or infinite"),
    (lambda d: d.__setitem__((2, 5, 0), 3.0), "more than 1"),
])
def test_save_texcoords_refuses_non_finite_and_absurd_displacements(tmp_path, slid_sheet, damage, message):
    tc, d, a = _texcoord_arrays(slid_sheet)
    damage(d["b"])
    out = tmp_path / "tc"
    with pytest.raises(mvtex.OptionError, match=rf"displacement\['b'\].*{message}"):
        mvtex.save_texcoords(out, faces=tc.faces, uv=tc.uv, parent=tc.parent, source="ts", subdiv=tc.subdiv,
                             poses=tc.poses, displacement=d, assigned=a)
    assert not out.exists() and not list(tmp_path.iterdir())


def test_what_save_texcoords_writes_opens(tmp_path, slid_sheet):
    tc, d, a = _texcoord_arrays(slid_sheet)
    out = mvtex.save_texcoords(tmp_path / "tc", faces=tc.faces, uv=tc.uv, parent=tc.parent, source="ts",
                               subdiv=tc.subdiv, poses=tc.poses, displacement=d, assigned=a)
    back = mvtex.open_texcoords(out)
    np.testing.assert_array_equal(back.displacement("a", tc.poses[1]), d["a"][1])


@pytest.fixture
def overflowing_model(tmp_path, tiny_dataset):
    """A model whose weights are finite but whose output overflows float32 (every weight
    times 1e12): it loads, and predicts inf/NaN."""
    from helpers import fake_model
    from safetensors.torch import load_file, save_file

    model = fake_model(tmp_path / "model", tiny_dataset)
    state = load_file(str(model / "model.safetensors"))
    save_file({k: v * 1e12 if v.is_floating_point() else v for k, v in state.items()},
              str(model / "model.safetensors"))
    return model


def test_predict_refuses_a_model_that_predicts_non_finite_values(tmp_path, tiny_dataset, overflowing_model):
    out = tmp_path / "pred"
    with pytest.raises(mvtex.InputError, match=r"model.safetensors: predicts (NaN or infinite|a displacement)"):
        mvtex.predict(tiny_dataset, [overflowing_model], out, poses=[0, 1], progress=False)
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["model"]


def test_the_predict_command_refuses_a_model_that_predicts_non_finite_values(tmp_path, capsys, tiny_dataset,
                                                                              overflowing_model):
    out = tmp_path / "pred"
    code, _, err = run(capsys, "predict", tiny_dataset, "--model", overflowing_model, "--out", out, "--poses", "0,1")
    one_line_error(code, err, "model.safetensors", "camera 'a'")
    assert not out.exists()


# -- typed errors naming the argument ----------------------------------------------------------

def test_an_unknown_camera_is_a_typed_error_naming_it(front_rig):
    with pytest.raises(mvtex.OptionError, match="no camera named 'zz'") as caught:
        front_rig["zz"]
    assert isinstance(caught.value, KeyError)  # `except KeyError` keeps working


@pytest.mark.parametrize("call, name", [
    (lambda rig, ds: mvtex.project_points([1, 2], np.zeros((2, 3))), "cameras"),
    (lambda rig, ds: mvtex.project_points(list(rig), "points"), "points"),
    (lambda rig, ds: mvtex.triangulate_points(list(rig), np.zeros((2, 2, 2)), np.ones((2, 3))), "weights"),
    (lambda rig, ds: mvtex.interpolate_camera(rig, {"a": "half", "b": 0.5}, "v"), "weights"),
    (lambda rig, ds: mvtex.triangulate_pose(ds, rig, "no-such-set", "3", None), "pose"),
    (lambda rig, ds: mvtex.slide_dataset(ds, rig, None, poses=[0], options=mvtex.SlideOptions()), "out"),
    (lambda rig, ds: mvtex.slide_dataset(ds, rig, "x", poses=[0], options={"subdiv": 1}), "options"),
    (lambda rig, ds: mvtex.SlideOptions(subdiv="1"), "subdiv"),
    (lambda rig, ds: mvtex.ReconOptions(max_reprojection_px=None), "max_reprojection_px"),
    (lambda rig, ds: mvtex.Rig([rig, rig]), "cameras"),
    (lambda rig, ds: mvtex.load_dataset(None), "path"),
])
def test_a_wrong_argument_is_a_typed_error_naming_it(call, name, front_rig, tiny_dataset):
    with pytest.raises(mvtex.OptionError, match=rf"^{name}\b"):
        call(front_rig, mvtex.load_dataset(tiny_dataset))


# -- a --scheduler that is not a Dask scheduler ------------------------------------------------

@pytest.fixture
def silent_server():
    """A TCP port on 127.0.0.1 that accepts connections and never says a word."""
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(8)
    held = []

    def accept():
        while True:
            try:
                held.append(server.accept()[0])
            except OSError:
                return

    threading.Thread(target=accept, daemon=True).start()
    yield f"tcp://127.0.0.1:{server.getsockname()[1]}"
    server.close()
    for conn in held:
        conn.close()


def _within(seconds: float, call):
    """Run call() in a thread; fail (instead of hanging the suite) when it does not return."""
    box = {}

    def target():
        try:
            box["value"] = call()
        except BaseException as err:  # noqa: BLE001 - handed to the test
            box["error"] = err

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    thread.join(seconds)
    assert not thread.is_alive(), f"still running after {seconds} s: a hang"
    if "error" in box:
        raise box["error"]
    return box.get("value")


@pytest.mark.slow
def test_a_silent_scheduler_is_refused_by_the_library(tmp_path, monkeypatch, silent_server, tiny_dataset, front_rig):
    monkeypatch.setattr("mvtex.util.parallel.SCHEDULER_TIMEOUT_S", 1.0)
    with pytest.raises(mvtex.OptionError, match="not a Dask scheduler"):
        _within(60, lambda: mvtex.slide_dataset(tiny_dataset, front_rig, tmp_path / "ts", poses=[0],
                                                options=mvtex.SlideOptions(subdiv=0), scheduler=silent_server,
                                                progress=False))
    assert not list(tmp_path.iterdir())


@pytest.mark.slow
def test_a_silent_scheduler_is_refused_by_the_command_line(tmp_path, capsys, monkeypatch, silent_server,
                                                           tiny_dataset, rig_file):
    monkeypatch.setattr("mvtex.util.parallel.SCHEDULER_TIMEOUT_S", 1.0)
    out = tmp_path / "ts"
    code, _, err = _within(60, lambda: run(capsys, "slide", tiny_dataset, "--rig", rig_file, "--out", out,
                                           "--scheduler", silent_server, "--subdiv", 0))
    one_line_error(code, err, "--scheduler", "not a Dask scheduler")
    assert not list(tmp_path.iterdir())


# -- sizes bounded before memory is taken ------------------------------------------------------

def _png_header(path: Path, width: int, height: int) -> None:
    """A PNG whose header says width x height (8-bit gray) and whose pixel data is one
    compressed row: decoding it would take width x height bytes first."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\x00" * (width + 1)))
                     + chunk(b"IEND", b""))


def test_a_huge_png_is_refused_from_its_header(tmp_path):
    from mvtex.calibration.images import image_size, read_gray

    _png_header(tmp_path / "big.png", 32000, 32000)
    with pytest.raises(mvtex.InputError, match=r"big.png: image is 32000x32000"):
        read_gray(tmp_path / "big.png")
    _png_header(tmp_path / "ok.png", 640, 480)
    assert image_size(tmp_path / "ok.png") == (640, 480)


def test_calibrate_refuses_a_huge_png_from_its_header(tmp_path, capsys):
    _png_header(tmp_path / "images" / "cam0" / "f0.png", 32000, 24000)
    code, _, err = run(capsys, "calibrate", tmp_path / "images", "--board", "charuco:5x4:0.04:0.03:DICT_4X4_50",
                       "--out", tmp_path / "rig.yaml")
    one_line_error(code, err, "f0.png", "32000x24000")
    assert not (tmp_path / "rig.yaml").exists()


def test_workers_never_outnumber_the_cores():
    from mvtex.util.parallel import MAX_WORKERS, available_cores, check_backend, worker_count

    assert worker_count(64) == min(64, available_cores())
    assert worker_count(1) == 1
    with pytest.raises(mvtex.OptionError, match="workers"):
        check_backend(MAX_WORKERS + 1)


def test_a_camera_with_more_pixels_than_mvtex_renders_is_refused_before_rendering(tmp_path, capsys, tiny_dataset,
                                                                                  gl):
    from mvtex.data.camera import MAX_RENDER_PIXELS

    big = look_at("big", (0, 0.05, 1.2), (0, 0, 0), width=4000, height=4000, focal=6000.0)
    assert big.width * big.height > MAX_RENDER_PIXELS
    ds = mvtex.load_dataset(tiny_dataset)
    with pytest.raises(mvtex.InputError, match="4000x4000"):
        mvtex.rasterize(gl, np.asarray(ds.gt[0], np.float64), ds.faces, big)
    save_rig(Rig((big,)), tmp_path / "rig.yaml")
    code, _, err = run(capsys, "render", tiny_dataset, "--rig", tmp_path / "rig.yaml", "--pose", 0,
                       "--out", tmp_path / "render")
    one_line_error(code, err, "rig.yaml", "4000x4000", "megapixels")
    assert not (tmp_path / "render").exists()
