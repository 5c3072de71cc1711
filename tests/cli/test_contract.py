"""The contract every command keeps, one test per kind of breach: nothing lost or replaced
without --overwrite, one run per output, cameras made by mvtex pass its own checks, bad
names and counts refused before any work, one-line errors, inputs checked against what they
were made from."""

from __future__ import annotations

import dataclasses
import json
import os
import socket
import time

import numpy as np
import pytest
from helpers import grid_mesh, held_elsewhere, one_line_error, run, write_obj

from mvtex.data.rig import load_rig
from mvtex.util.output import MARKER, claim_file


def files(path):
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


def test_existing_files_are_kept_without_overwrite(tmp_path, capsys):
    photo = tmp_path / "photo.png"
    photo.write_bytes(b"\x89PNG a user's photo")
    rig = tmp_path / "calibrated.yaml"
    assert run(capsys, "rig", "square4", "--undistort", "--out", rig)[0] == 0
    before = rig.read_bytes()
    for argv in (["rig", "stereo", "--plot", photo], ["board", "charuco:5x4:0.04:0.03:DICT_4X4_50", "--out", photo],
                 ["rig", "stereo", "--undistort", "--out", rig], ["rig", "--from-colmap", tmp_path / "model", "--out", rig]):
        code, _, err = run(capsys, *argv)
        one_line_error(code, err, "exists", "--overwrite")
    # An input is never its own output, --overwrite or not: the calibrated distortion stays.
    code, _, err = run(capsys, "rig", rig, "--undistort", "--out", rig, "--overwrite")
    one_line_error(code, err, "also an input")
    assert photo.read_bytes() == b"\x89PNG a user's photo" and rig.read_bytes() == before
    assert run(capsys, "rig", "stereo", "--plot", photo, "--overwrite")[0] == 0 and photo.read_bytes() != before


def test_one_run_per_output_file(tmp_path, capsys):
    out = tmp_path / "board.png"
    with held_elsewhere(claim_file(out, "board")):
        code, _, err = run(capsys, "board", "charuco:5x4:0.04:0.03:DICT_4X4_50", "--out", out)
    one_line_error(code, err, f"in use by pid {os.getpid()}")
    assert not out.exists()


def test_interpolated_cameras_pass_the_camera_checks(tmp_path, capsys):
    from mvtex.views.cameras import grid_weights, interpolate_camera

    rig = load_rig("square4")
    rng = np.random.default_rng(0)
    mixes = [dict(zip(rig.names, rng.dirichlet(np.ones(4)))) for _ in range(200)] + grid_weights(*rig.names, 7)
    for w in mixes:
        total = sum(w.values())
        cam = interpolate_camera(rig, {k: v / total for k, v in w.items()}, "v")
        assert np.all(cam.K[2] == (0, 0, 1)) and cam.K[1, 0] == 0
        assert np.abs(cam.R @ cam.R.T - np.eye(3)).max() < 1e-12 and np.linalg.det(cam.R) > 0
        centre = sum(v / total * rig[k].center for k, v in w.items())
        assert np.linalg.norm(cam.center - centre) < 1e-12


@pytest.mark.parametrize("flags, needle", [
    (["--between", "a,a", "--steps", 3], "two different cameras"),
    (["--grid", "a,b,a,b", "--steps", 3], "four different cameras"),
    (["--between", "a,b", "--steps", 100_000_000], "steps must be in 2.."),
    (["--grid", "a,b,a,b", "--steps", 1_000_000], "steps must be in 2.."),
])
def test_view_counts_and_repeats_refused_before_work(flags, needle, tmp_path, sheet_set, capsys):
    dataset, rig, ts = sheet_set
    code, _, err = run(capsys, "views", dataset, "--rig", rig, "--texcoords", ts, "--out", tmp_path / "v", *flags,
                       "--quiet")
    one_line_error(code, err, needle)
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("name", ["cam 2", "kamera_ü", "mesh.npz", "-x"])
def test_calibration_folders_with_bad_camera_names_are_refused_before_detection(name, tmp_path, capsys, monkeypatch):
    import cv2

    import mvtex.calibration.board

    def never(*args, **kwargs):
        raise AssertionError("detection ran")

    monkeypatch.setattr(mvtex.calibration.board.BoardDetector, "detect", never)
    for folder in ("cam0", name):
        (tmp_path / "images" / folder).mkdir(parents=True)
        cv2.imwrite(str(tmp_path / "images" / folder / "f0.png"), np.zeros((8, 8), np.uint8))
    code, _, err = run(capsys, "calibrate", tmp_path / "images", "--board", "charuco:5x4:0.04:0.03:DICT_4X4_50",
                       "--out", tmp_path / "rig.yaml", "--quiet")
    one_line_error(code, err, name)
    assert not (tmp_path / "rig.yaml").exists()


def test_case_twins_among_calibration_folders_are_refused(tmp_path, capsys):
    for folder in ("cam0", "CAM0"):
        (tmp_path / "images" / folder).mkdir(parents=True)
        (tmp_path / "images" / folder / "f0.png").write_bytes(b"")
    code, _, err = run(capsys, "calibrate", tmp_path / "images", "--board", "charuco:5x4:0.04:0.03:DICT_4X4_50",
                       "--out", tmp_path / "rig.yaml", "--quiet")
    one_line_error(code, err, "differ only in case")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("address", ["banana", "tcp://127.0.0.1:{port}"])
def test_a_bad_scheduler_is_refused_at_once_and_leaves_nothing(address, tmp_path, tiny_dataset, rig_file, capsys):
    address = address.format(port=_free_port())
    start = time.monotonic()
    code, _, err = run(capsys, "slide", tiny_dataset, "--rig", rig_file, "--out", tmp_path / "tc", "--scheduler",
                       address, "--quiet")
    one_line_error(code, err, "--scheduler")
    assert time.monotonic() - start < 10 and not list(tmp_path.iterdir())


def test_counts_are_bounded_before_allocation(tmp_path, tiny_dataset, rig_file, capsys):
    code, _, err = run(capsys, "board", "charuco:9x6:0.05:0.0375:DICT_5X5_100", "--out", tmp_path / "b.png",
                       "--pixels-per-square", 1_000_000)
    one_line_error(code, err, "--pixels-per-square")
    code, _, err = run(capsys, "slide", tiny_dataset, "--rig", rig_file, "--out", tmp_path / "tc", "--workers",
                       10 ** 9, "--quiet")
    one_line_error(code, err, "--workers")
    assert not list(tmp_path.iterdir())


def test_preview_eyes_that_see_no_cloth_are_an_error_not_a_perfect_score(tmp_path, sheet_set, capsys):
    dataset, rig, ts = sheet_set
    for ipd in (9.9, 5):
        code, out, err = run(capsys, "preview", dataset, "--rig", rig, "--texcoords", ts, "--pose", 0, "--out",
                             tmp_path / "p", "--ipd", ipd, "--json", "--quiet")
        one_line_error(code, err, "--ipd", "sees none of the cloth")
        assert out == "" and not (tmp_path / "p").exists()


@pytest.mark.parametrize("argv", [["slide", "--bogus"], ["slide"], ["eval", "x", "--rig"], ["bogus"],
                                  ["train", "d", "--texcoords", "t", "--out", "o", "--arch", "banana"]])
def test_usage_errors_are_one_line(argv, capsys):
    code, out, err = run(capsys, *argv)
    line = one_line_error(code, err)
    assert "--help" in line and err.count("\n") == 1 and out == ""


@pytest.mark.parametrize("content, needle", [
    (bytes(range(256)) * 8, "not a text OBJ"),
    (b"v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n", "a face of 4 vertices"),
    (b"v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2 9\n", "out of range"),
])
def test_unreadable_meshes_are_one_line_naming_the_problem(content, needle, tmp_path, capsys):
    (tmp_path / "g0.obj").write_bytes(content)
    code, _, err = run(capsys, "import", "--out", tmp_path / "ds", "--gt", tmp_path / "g*.obj", "--inferred",
                       tmp_path / "g*.obj", "--quiet")
    one_line_error(code, err, "g0.obj", needle)
    assert err.count("\n") == 1  # no library warnings besides it


def test_a_stray_file_in_an_import_glob_is_named(tmp_path, capsys):
    faces, uv, rest = grid_mesh(4, 4)
    for k in range(2):
        write_obj(tmp_path / f"m{k}.obj", rest, uv, faces)
    (tmp_path / "README.txt").write_text("notes")
    code, _, err = run(capsys, "import", "--out", tmp_path / "ds", "--gt", tmp_path / "*", "--inferred",
                       tmp_path / "m*.obj", "--quiet")
    one_line_error(code, err, "README.txt", "not an OBJ or PLY")


def test_a_set_of_another_dataset_or_rig_is_refused(tmp_path, tiny_dataset, slid_sheet0, rig_file, capsys):
    from mvtex.data.dataset import load_dataset, save_dataset
    from mvtex.data.rig import Rig, save_rig

    ds = load_dataset(tiny_dataset)
    other = tmp_path / "other"  # the same mesh, other content
    save_dataset(other, faces=ds.faces, uv=ds.uv, gt=np.asarray(ds.gt)[::-1], inferred=np.asarray(ds.inferred),
                 poses=np.asarray(ds.poses), rest=ds.rest)
    for argv in (["eval", other, "--rig", rig_file, "--texcoords", slid_sheet0],
                 ["render", other, "--rig", rig_file, "--texcoords", slid_sheet0, "--pose", 0, "--out", tmp_path / "r"],
                 ["views", other, "--rig", rig_file, "--texcoords", slid_sheet0, "--weights", "a=0.5,b=0.5",
                  "--method", "blend", "--out", tmp_path / "v"],
                 ["triangulate", other, "--rig", rig_file, "--texcoords", slid_sheet0, "--pose", 0, "--out",
                  tmp_path / "t"]):
        code, _, err = run(capsys, *argv, "--quiet")
        one_line_error(code, err, "texcoords.json", "another dataset")
    moved = load_rig(rig_file)
    moved = Rig(tuple(c if c.name != "b" else type(c)(c.name, c.width, c.height, c.K, c.R, c.t + [0.01, 0, 0])
                      for c in moved))
    save_rig(moved, tmp_path / "moved.yaml")
    for argv in (["eval", tiny_dataset, "--rig", tmp_path / "moved.yaml", "--texcoords", slid_sheet0],
                 ["triangulate", tiny_dataset, "--rig", tmp_path / "moved.yaml", "--texcoords", slid_sheet0,
                  "--pose", 0, "--out", tmp_path / "t"]):
        code, _, err = run(capsys, *argv, "--quiet")
        one_line_error(code, err, "camera 'b'", "other parameters")
    assert not (tmp_path / "r").exists() and not (tmp_path / "v").exists() and not (tmp_path / "t").exists()


@pytest.mark.parametrize("spec, needle", [("1,1", "twice"), ("0:100", "reaches past"), ("-100:", "reaches past")])
def test_pose_specs_are_not_clamped_or_repeated(spec, needle, tmp_path, tiny_dataset, rig_file, capsys):
    code, _, err = run(capsys, "slide", tiny_dataset, "--rig", rig_file, "--out", tmp_path / "tc", f"--poses={spec}",
                       "--quiet")
    one_line_error(code, err, needle)


def test_a_zero_quaternion_in_a_colmap_model_is_refused(tmp_path, capsys):
    assert run(capsys, "rig", "stereo", "--to-colmap", tmp_path / "m", "--text")[0] == 0
    frames = tmp_path / "m" / "frames.txt"
    lines = frames.read_text().splitlines()
    data = [i for i, line in enumerate(lines) if line and not line.startswith("#")]
    fields = lines[data[0]].split()
    fields[2:6] = ["0", "0", "0", "0"]
    lines[data[0]] = " ".join(fields)
    frames.write_text("\n".join(lines) + "\n")
    code, _, err = run(capsys, "rig", "--from-colmap", tmp_path / "m", "--out", tmp_path / "r.yaml")
    one_line_error(code, err, "not a rigid transform")
    assert not (tmp_path / "r.yaml").exists()


def test_leftovers_of_a_killed_run_go_and_outputs_are_readable(tmp_path, capsys):
    # As if a run had been killed between writing its temporaries and renaming them in.
    from mvtex.util.output import _temporary

    _temporary(tmp_path / "board.png", "tmp")  # what killed runs leave: named and stamped as mvtex's
    _temporary(tmp_path / "und", "tmp")
    assert run(capsys, "board", "charuco:5x4:0.04:0.03:DICT_4X4_50", "--out", tmp_path / "board.png")[0] == 0
    (tmp_path / "imgs" / "left").mkdir(parents=True)
    import cv2

    cv2.imwrite(str(tmp_path / "imgs" / "left" / "a.png"), np.zeros((512, 512), np.uint8))
    assert run(capsys, "undistort", tmp_path / "imgs", "--rig", "stereo", "--out", tmp_path / "und", "--quiet")[0] == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["board.png", "imgs", "und"]
    umask = os.umask(0)
    os.umask(umask)
    assert (tmp_path / "board.png").stat().st_mode & 0o777 == 0o666 & ~umask


def test_model_files_have_the_modes_of_other_outputs(tmp_path, tiny_dataset):
    pytest.importorskip("torch")
    from helpers import fake_model

    from mvtex.tsnn.modeldir import _write_model
    from mvtex.tsnn.predict import load_model

    model = load_model(fake_model(tmp_path / "m", tiny_dataset))
    config = dataclasses.replace(model.config, history={"train": [1.0], "val": [1.0]}, best_epoch=1)
    _write_model(tmp_path / "again", model.network, config)
    modes = {p.name: p.stat().st_mode & 0o777 for p in (tmp_path / "again").iterdir()}
    assert modes["model.safetensors"] == modes["config.json"], modes


def test_messages_name_the_file_once_and_in_order(tmp_path, capsys):
    rig = tmp_path / "x.yaml"
    rig.write_text('%YAML:1.0\nformat: "mvtex-rig"\nversion: 1\ncameras:\n  - { name: a, width: 10, height: 10 }\n')
    code, _, err = run(capsys, "rig", rig)
    line = one_line_error(code, err, "missing 'R'")
    assert line.count(str(rig)) == 1
    code, _, err = run(capsys, "board", "charuco:9x6:-0.05:0.03:DICT_4X4_50", "--out", tmp_path / "b.png")
    one_line_error(code, err, "SQUARE_M -0.05 and MARKER_M 0.03")


@pytest.mark.parametrize("argv", [["synth", "--help"], ["board", "--help"], ["rig", "--help"]])
def test_every_command_takes_quiet_json_and_overwrite(argv, capsys):
    code, out, _ = run(capsys, *argv)
    assert code == 0 and "--quiet" in out and "--json" in out and "--overwrite" in out


def test_a_marker_is_written_into_claimed_folders(tmp_path, capsys):
    (tmp_path / "imgs" / "left").mkdir(parents=True)
    import cv2

    cv2.imwrite(str(tmp_path / "imgs" / "left" / "a.png"), np.zeros((512, 512), np.uint8))
    assert run(capsys, "undistort", tmp_path / "imgs", "--rig", "stereo", "--out", tmp_path / "u", "--quiet")[0] == 0
    assert json.loads((tmp_path / "u" / MARKER).read_text())["command"] == "undistort"
    before = files(tmp_path / "u")
    assert run(capsys, "undistort", tmp_path / "imgs", "--rig", "stereo", "--out", tmp_path / "u", "--quiet")[0] == 0
    assert files(tmp_path / "u") == before  # its own output: replaced by the same
