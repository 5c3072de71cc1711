"""Calibration: a ChArUco board rendered with moderngl from a known 4-camera rig (the rig
of examples/calibrate_rig.py) is calibrated back through `mvtex calibrate`; boards,
undistortion and COLMAP rigs are checked against OpenCV and pycolmap computations."""

from __future__ import annotations

import importlib.util
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from mvtex.calibration.board import BoardDetector, board_image, parse_board_spec
from mvtex.cli import main
from mvtex.data.camera import Camera
from mvtex.data.rig import Rig, load_rig, save_rig

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def _example():
    spec = importlib.util.spec_from_file_location("calibrate_rig", EXAMPLES / "calibrate_rig.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


example = _example()
SPEC = example.SPEC  # charuco:9x6:0.05:0.0375:DICT_4X4_50
NUM_POSES = 12


@pytest.fixture(scope="session")
def board_images(tmp_path_factory, gl):
    """The example's rig (4 cameras, 640x480, cam2 with barrel distortion) and its images
    of 12 board poses (noise sigma 2 gray levels), plus a frame of cam1 without the board."""
    rig = example.true_rig()
    folder = tmp_path_factory.mktemp("calib") / "images"
    example.render_images(rig, folder, NUM_POSES)
    cv2.imwrite(str(folder / "cam1" / "frame_blank.png"), np.full((480, 640), 90, np.uint8))
    return folder, rig


@pytest.fixture(scope="session")
def calibrated(board_images, tmp_path_factory):
    folder, rig = board_images
    out = tmp_path_factory.mktemp("calib_out") / "rig.yaml"
    return out, rig, _run_json(["calibrate", str(folder), "--board", SPEC, "--out", str(out),
                                "--pictures", str(out.with_name("rig_calibration")), "--quiet", "--json"])


def _run_json(argv) -> dict:
    import contextlib
    import io

    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        code = main(argv)
    assert code == 0, stdout.getvalue()
    return json.loads(stdout.getvalue())


def _fails(argv, capsys, *fragments) -> str:
    code = main(argv)
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert len(err.splitlines()) == 1, err
    for fragment in fragments:
        assert fragment in err, err
    return err


def _relative(cam: Camera, ref: Camera) -> np.ndarray:
    """(4,4) cam_from_ref."""
    a, b = np.eye(4), np.eye(4)
    a[:3] = cam.cam_from_world
    b[:3] = ref.cam_from_world
    return a @ np.linalg.inv(b)


@pytest.mark.slow
@pytest.mark.gl
def test_calibrate_recovers_the_rig(calibrated):
    out, truth, result = calibrated
    rig = load_rig(out)
    assert rig.names == truth.names
    assert result["num_cameras"] == 4 and result["num_frames"] == NUM_POSES
    assert result["reference"] == "cam0"
    assert result["per_camera"]["cam1"]["skipped"] == 1
    assert all(c["frames"] == NUM_POSES for c in result["per_camera"].values())
    assert 0 < result["rms_reprojection_px"] < 0.3
    for cam in rig:
        true = truth[cam.name]
        assert (cam.width, cam.height) == (640, 480)
        focal_error = np.abs(np.diag(cam.K)[:2] / np.diag(true.K)[:2] - 1)
        assert focal_error.max() < 0.005, (cam.name, cam.K, true.K)
        assert np.abs(cam.K[:2, 2] - true.K[:2, 2]).max() < 2.0, (cam.name, cam.K, true.K)
        # World frame = cam0's frame: compare each camera's pose relative to cam0.
        expected = _relative(true, truth["cam0"])
        dR = expected[:3, :3].T @ cam.R
        angle = np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))
        assert angle < 0.2, (cam.name, angle)
        assert np.linalg.norm(cam.t - expected[:3, 3]) < 0.002, (cam.name, cam.t, expected[:3, 3])
        # Distortion: where the lens moves a pixel at the image corner, the fit moves it alike.
        corner = np.array([[[0.0, 0.0]]])
        moved = [cv2.undistortPoints(corner, c.K, c.dist, P=c.K).reshape(2) for c in (cam, true)]
        assert np.linalg.norm(moved[0] - moved[1]) < 1.0, (cam.name, cam.dist, true.dist, moved)


@pytest.mark.slow
@pytest.mark.gl
def test_calibration_record_and_pictures(calibrated):
    out, _, result = calibrated
    folder = out.with_name("rig_calibration")
    record = json.loads((folder / "calibration.json").read_text())
    assert record["format"] == "mvtex-calibration"
    assert record["options"]["board"] == SPEC
    assert record["cameras"]["cam1"]["skipped"] == ["frame_blank"]
    assert record["per_camera"] == result["per_camera"]
    for name in ("rig.png", "residuals.png"):
        image = cv2.imread(str(folder / name))
        assert image is not None and image.shape[0] > 400
        assert image.std() > 10  # not a blank canvas


def test_projection_matches_opencv():
    from mvtex.calibration.calibrate import project_distorted

    rng = np.random.default_rng(3)
    points = rng.uniform(-0.3, 0.3, (50, 3)) + [0, 0, 1.2]
    rvec, tvec = np.array([0.1, -0.2, 0.05]), np.array([0.02, -0.01, 0.1])
    intrinsics = np.array([610.0, 605.0, 320.0, 241.0, -0.21, 0.08, 0.001, -0.002, 0.01])
    K = np.array([[610.0, 0, 320], [0, 605, 241], [0, 0, 1]])
    expected, _ = cv2.projectPoints(points, rvec, tvec, K, intrinsics[4:])
    np.testing.assert_allclose(project_distorted(points, rvec, tvec, intrinsics), expected.reshape(-1, 2), atol=1e-9)


@pytest.mark.gl
def test_camera_sharing_no_frame_is_named(board_images, tmp_path, capsys):
    folder, _ = board_images
    images = tmp_path / "images"
    for cam, frames in (("cam0", range(0, 6)), ("cam1", range(0, 6)), ("cam2", range(6, 12))):
        (images / cam).mkdir(parents=True)
        for f in frames:
            shutil.copy(folder / cam / f"frame_{f:03d}.png", images / cam)
    _fails(["calibrate", str(images), "--board", SPEC, "--out", str(tmp_path / "rig.yaml"), "--quiet"], capsys,
           "camera cam2 shares no frame")
    assert not (tmp_path / "rig.yaml").exists()


@pytest.mark.slow
@pytest.mark.gl
def test_cameras_linked_through_another_camera(board_images, tmp_path):
    """cam0 and cam2 share no frame, but both share frames with cam1: cam2's pose reaches
    the reference through cam1."""
    folder, truth = board_images
    images = tmp_path / "images"
    for cam, frames in (("cam0", range(0, 6)), ("cam1", range(0, 12)), ("cam2", range(6, 12))):
        (images / cam).mkdir(parents=True)
        for f in frames:
            shutil.copy(folder / cam / f"frame_{f:03d}.png", images / cam)
    out = tmp_path / "rig.yaml"
    result = _run_json(["calibrate", str(images), "--board", SPEC, "--out", str(out), "--quiet", "--json"])
    assert result["num_frames"] == 12 and result["per_camera"]["cam2"]["frames"] == 6
    rig = load_rig(out)
    expected = _relative(truth["cam2"], truth["cam0"])
    dR = expected[:3, :3].T @ rig["cam2"].R
    assert np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))) < 0.3
    assert np.linalg.norm(rig["cam2"].t - expected[:3, 3]) < 0.003


def test_bad_input_exits_2_with_one_line(tmp_path, capsys):
    out = str(tmp_path / "out" / "rig.yaml")
    empty = tmp_path / "empty"
    empty.mkdir()
    _fails(["calibrate", str(empty), "--board", SPEC, "--out", out], capsys, str(empty), "no images")
    broken = tmp_path / "broken" / "cam0"
    broken.mkdir(parents=True)
    (broken / "frame_000.png").write_bytes(b"not a png")
    _fails(["calibrate", str(broken.parent), "--board", SPEC, "--out", out, "--quiet"], capsys,
           "frame_000.png", "cannot be read")
    _fails(["calibrate", str(empty), "--board", "charuco:9x6:0.05", "--out", out], capsys, "does not parse")
    _fails(["calibrate", str(empty), "--board", "charuco:9x6:0.05:0.06:DICT_4X4_50", "--out", out], capsys, "MARKER_M")
    _fails(["calibrate", str(empty), "--board", "charuco:9x6:0.05:0.03:DICT_9X9_1", "--out", out], capsys,
           "unknown dictionary")
    blank = tmp_path / "blank"
    for cam in ("a", "b"):
        (blank / cam).mkdir(parents=True)
        for f in range(3):
            cv2.imwrite(str(blank / cam / f"{f}.png"), np.full((120, 160), 128, np.uint8))
    _fails(["calibrate", str(blank), "--board", SPEC, "--out", out, "--quiet"], capsys, "camera a",
           "the board is never found")
    assert not (tmp_path / "out").exists()


def test_existing_outputs_are_not_replaced_without_overwrite(tmp_path, capsys):
    foreign = tmp_path / "notes.yaml"
    foreign.write_text("my notes\n")
    _fails(["calibrate", str(tmp_path / "images"), "--board", SPEC, "--out", str(foreign)], capsys, "exists",
           "--overwrite")
    _fails(["calibrate", str(tmp_path), "--board", SPEC, "--out", str(foreign), "--overwrite"], capsys,
           "lies inside the input")  # a file in the image folder is part of the input
    _fails(["board", SPEC, "--out", str(foreign)], capsys, "exists", "--overwrite")
    _fails(["rig", "stereo", "--undistort", "--out", str(foreign)], capsys, "exists", "--overwrite")
    _fails(["rig", "stereo", "--plot", str(foreign)], capsys, "exists", "--overwrite")
    (tmp_path / "images").mkdir()
    _fails(["undistort", str(tmp_path / "images"), "--rig", "stereo", "--out", str(tmp_path)], capsys,
           "contains the input")  # the folder holds the images it would read
    assert foreign.read_text() == "my notes\n"
    # An mvtex rig is an mvtex rig, but it may be last week's calibration: --overwrite it is.
    main(["rig", "stereo", "--undistort", "--out", str(tmp_path / "pinhole.yaml")])
    _fails(["rig", "stereo", "--undistort", "--out", str(tmp_path / "pinhole.yaml")], capsys, "exists")
    assert main(["rig", "stereo", "--undistort", "--out", str(tmp_path / "pinhole.yaml"), "--overwrite"]) == 0
    # An input is never its own output, not even with --overwrite.
    _fails(["rig", str(tmp_path / "pinhole.yaml"), "--undistort", "--out", str(tmp_path / "pinhole.yaml"),
            "--overwrite"], capsys, "is also an input")


def test_board_png_prints_to_scale_and_detects(tmp_path):
    from PIL import Image

    out = tmp_path / "board.png"
    result = _run_json(["board", SPEC, "--out", str(out), "--dpi", "200", "--json"])
    with Image.open(out) as image:
        dpi = image.info["dpi"][0]
        gray = np.asarray(image.convert("L"))
    pps = result["pixels_per_square"]
    assert abs(pps / dpi * 25.4 - 50.0) < 0.5  # a printed square measures 50 mm
    spec = parse_board_spec(SPEC)
    small = cv2.resize(gray, None, fx=0.25, fy=0.25, interpolation=cv2.INTER_AREA)
    detection = BoardDetector(spec).detect(small)
    assert len(detection) == spec.num_corners
    # Corner (i, j) lies where the board's own geometry puts it: margin + (k + 1) squares.
    margin = (gray.shape[1] - spec.cols * pps) / 2
    cols = detection.ids % (spec.cols - 1) + 1
    rows = detection.ids // (spec.cols - 1) + 1
    expected = (np.stack([cols, rows], 1) * pps + margin) * 0.25 - 0.5
    np.testing.assert_allclose(detection.pixels, expected, atol=0.15)
    assert main(["board", SPEC, "--out", str(out), "--pixels-per-square", "40"]) == 2  # an existing file...
    assert main(["board", SPEC, "--out", str(out), "--pixels-per-square", "40", "--overwrite"]) == 0  # ...on request


def test_board_image_geometry():
    spec = parse_board_spec(SPEC)
    image = board_image(spec, 20, margin_px=10)
    assert image.shape == (6 * 20 + 20, 9 * 20 + 20)
    assert image[10, 10] == 0 and image[5, 5] == 255  # first square black, margin white


def _distorted_camera() -> Camera:
    K = np.array([[400.0, 0, 161.0], [0, 402.0, 119.0], [0, 0, 1]])
    return Camera("cam0", 320, 240, K=K, R=np.eye(3), t=np.zeros(3), dist=np.array([-0.28, 0.09, 0.001, -0.0015, 0]))


def test_undistort_moves_points_to_their_pinhole_projection(tmp_path):
    """Dots drawn where cv2.projectPoints puts them *with* distortion land, after
    `mvtex undistort`, where the pinhole projection (same K) puts them."""
    camera = _distorted_camera()
    rig_path = tmp_path / "rig.yaml"
    save_rig(Rig((camera,)), rig_path)
    gx, gy = np.meshgrid(np.linspace(-0.28, 0.28, 7), np.linspace(-0.2, 0.2, 5))
    points = np.stack([gx.ravel(), gy.ravel(), np.ones(gx.size)], 1)
    distorted, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), camera.K, camera.dist)
    image = np.zeros((240, 320), np.uint8)
    scale = 16
    for u, v in distorted.reshape(-1, 2):  # sub-pixel dots: anti-aliased circles in fixed point
        cv2.circle(image, (int(round(u * scale)), int(round(v * scale))), 2 * scale, 255, -1, cv2.LINE_AA, shift=4)
    (tmp_path / "images" / "cam0").mkdir(parents=True)
    cv2.imwrite(str(tmp_path / "images" / "cam0" / "dots.png"), image)
    out = tmp_path / "undistorted"
    result = _run_json(["undistort", str(tmp_path / "images"), "--rig", str(rig_path), "--out", str(out), "--quiet",
                        "--json"])
    assert result["num_images"] == 1
    pinhole = load_rig(out / "rig.yaml")["cam0"]
    assert np.all(pinhole.dist == 0) and np.allclose(pinhole.K, camera.K)
    undistorted = cv2.imread(str(out / "cam0" / "dots.png"), cv2.IMREAD_GRAYSCALE).astype(np.float64)
    expected = points[:, :2] / points[:, 2:] * np.diag(camera.K)[:2] + camera.K[:2, 2]
    v, u = np.mgrid[:240, :320]
    for x, y in expected:
        window = (np.abs(u - x) < 6) & (np.abs(v - y) < 6)
        weight = undistorted * window
        centroid = np.array([(weight * u).sum(), (weight * v).sum()]) / weight.sum()
        assert np.linalg.norm(centroid - (x, y)) < 0.25, (centroid, (x, y))


def test_rig_undistort_and_alpha(tmp_path):
    camera = _distorted_camera()
    save_rig(Rig((camera,)), tmp_path / "rig.yaml")
    _run_json(["rig", str(tmp_path / "rig.yaml"), "--undistort", "--out", str(tmp_path / "same.yaml"), "--json"])
    same = load_rig(tmp_path / "same.yaml")["cam0"]
    assert np.allclose(same.K, camera.K) and np.all(same.dist == 0)
    _run_json(["rig", str(tmp_path / "rig.yaml"), "--undistort", "--alpha", "0", "--out", str(tmp_path / "crop.yaml"),
               "--json"])
    crop = load_rig(tmp_path / "crop.yaml")["cam0"]
    # alpha 0: every pixel of the undistorted image comes from inside the input image.
    from mvtex.data.camera import undistort_image

    white = undistort_image(np.full((240, 320), 255, np.uint8), camera, crop)
    assert white[2:-2, 2:-2].min() > 250


def test_rig_colmap_round_trip(tmp_path, capsys):
    import pycolmap

    from mvtex.data.rig import builtin_rig_file

    rig = load_rig(builtin_rig_file("square4"))
    model = tmp_path / "model"
    _run_json(["rig", "square4", "--to-colmap", str(model), "--json"])
    rec = pycolmap.Reconstruction(str(model))
    point = np.array([0.05, -0.03, 0.1])
    for image in rec.images.values():
        cam = rig[image.name.rsplit(".", 1)[0]]
        expected, _ = cv2.projectPoints(point[None], cv2.Rodrigues(cam.R)[0], cam.t, cam.K, None)
        projected = rec.cameras[image.camera_id].img_from_cam(image.cam_from_world() * point)
        np.testing.assert_allclose(projected, expected.reshape(2) + 0.5, atol=1e-6)  # COLMAP's +0.5
    back = tmp_path / "back.yaml"
    _run_json(["rig", "--from-colmap", str(model), "--out", str(back), "--json"])
    for cam in load_rig(back):
        np.testing.assert_allclose(cam.K, rig[cam.name].K, atol=1e-9)
        np.testing.assert_allclose(cam.R, rig[cam.name].R, atol=1e-9)
        np.testing.assert_allclose(cam.t, rig[cam.name].t, atol=1e-9)
    save_rig(Rig((_distorted_camera(),)), tmp_path / "distorted.yaml")
    _fails(["rig", str(tmp_path / "distorted.yaml"), "--to-colmap", str(tmp_path / "m2")], capsys,
           "distortion", "--undistort")
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "notes.txt").write_text("keep")
    _fails(["rig", "square4", "--to-colmap", str(tmp_path / "busy")], capsys, "mvtex did not write")
    assert (tmp_path / "busy" / "notes.txt").read_text() == "keep"


def test_rig_summary_and_plot(tmp_path):
    from mvtex.data.rig import builtin_rig_file

    rig = load_rig(builtin_rig_file("stereo"))
    summary = _run_json(["rig", "stereo", "--json"])
    baseline = np.linalg.norm(rig.cameras[0].center - rig.cameras[1].center)
    assert summary["num_cameras"] == 2 and abs(summary["baseline_m"]["max"] - baseline) < 1e-12
    _run_json(["rig", "trapezoid12", "--plot", str(tmp_path / "rig.png"), "--json"])
    assert cv2.imread(str(tmp_path / "rig.png")).std() > 10


@pytest.mark.slow
@pytest.mark.gl
def test_example_runs_every_step(tmp_path, gl):
    result = example.main(tmp_path / "demo", num_poses=4)
    assert all(c["frames"] == 4 for c in result["calibrate"]["per_camera"].values())
    for path in ("board.png", "rig.yaml", "rig_pinhole.yaml", "rig_calibration/rig.png", "undistorted/rig.yaml",
                 "undistorted/cam2/frame_003.png", "colmap/cameras.bin"):
        assert (tmp_path / "demo" / path).is_file(), path
