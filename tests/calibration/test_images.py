"""The images `calibrate` and `undistort` read, through `mvtex.cli.main(argv)`: a damaged
picture is one line naming it, with nothing from libpng or libjpeg on stderr (captured at the
file descriptor, where those libraries write), a truncated JPEG is refused rather than
decoded in part, and the odd image of a camera is the one named."""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers import one_line_error, run

BOARD = "charuco:5x4:0.04:0.03:DICT_4X4_50"


def noise(height: int, width: int, channels: int = 3, dtype=np.uint8, seed: int = 0) -> np.ndarray:
    top = np.iinfo(dtype).max
    shape = (height, width, channels) if channels > 1 else (height, width)
    return (np.random.default_rng(seed).random(shape) * top).astype(dtype)


def truncated_jpeg(path: Path, image: np.ndarray) -> Path:
    ok, buf = cv2.imencode(".jpg", image)
    path.write_bytes(buf.tobytes()[: len(buf) // 2])
    return path


def bad_crc_png(path: Path, image: np.ndarray) -> Path:
    """A PNG whose text chunk has a wrong checksum: libpng warns on stderr and decodes it."""
    ok, buf = cv2.imencode(".png", image)
    data = buf.tobytes()
    chunk = b"tEXtComment\x00hello"
    path.write_bytes(data[:33] + struct.pack(">I", len(chunk) - 4) + chunk + b"\0\0\0\0" + data[33:])
    return path


def truncated_png(path: Path, image: np.ndarray) -> Path:
    ok, buf = cv2.imencode(".png", image)
    path.write_bytes(buf.tobytes()[: len(buf) * 2 // 3])
    return path


DAMAGE = {"truncated.jpg": truncated_jpeg, "badcrc.png": bad_crc_png, "truncated.png": truncated_png}


@pytest.mark.parametrize("name", DAMAGE)
def test_a_damaged_picture_is_one_line_naming_it(name, tmp_path, capfd):
    images = tmp_path / "images"
    for cam in ("cam0", "cam1"):
        (images / cam).mkdir(parents=True)
        for frame in range(3):
            cv2.imwrite(str(images / cam / f"f{frame}.png"), noise(60, 80, seed=frame))
    bad = DAMAGE[name](images / "cam1" / f"f9{Path(name).suffix}", noise(60, 80))
    code, _, err = run(capfd, "calibrate", images, "--board", BOARD, "--out", tmp_path / "rig.yaml", "--quiet")
    one_line_error(code, err, bad, "cannot be read")
    assert len(err.strip().splitlines()) == 1, err  # nothing else: no libpng or libjpeg line
    # undistort reads every picture it is given: the same line for the same file
    (tmp_path / "und").mkdir()
    DAMAGE[name](tmp_path / "und" / f"left{Path(name).suffix}", noise(512, 512))
    code, _, err = run(capfd, "undistort", tmp_path / "und", "--rig", "stereo", "--out", tmp_path / "out", "--quiet")
    one_line_error(code, err, tmp_path / "und" / f"left{Path(name).suffix}", "cannot be read")
    assert len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "out").exists() and not (tmp_path / "rig.yaml").exists()


def test_the_odd_image_of_a_camera_is_the_one_named(tmp_path, capfd):
    images = tmp_path / "images"
    (images / "cam0").mkdir(parents=True)
    cv2.imwrite(str(images / "cam0" / "f0.png"), noise(60, 80))  # the odd one comes first
    for frame in (1, 2, 3):
        cv2.imwrite(str(images / "cam0" / f"f{frame}.png"), noise(120, 160, seed=frame))
    code, _, err = run(capfd, "calibrate", images, "--board", BOARD, "--out", tmp_path / "rig.yaml", "--quiet")
    line = one_line_error(code, err, images / "cam0" / "f0.png", "80x60", "160x120")
    assert "f1.png" not in line


@pytest.mark.parametrize("kind", ["gray8", "gray16", "rgb8", "rgba8", "rgb16", "jpeg"])
def test_pictures_decode_as_opencv_decodes_them(kind, tmp_path):
    """`read_image` gives the stored pixels (RGB order) and `read_gray` OpenCV's gray, for
    every kind of picture undistort and calibrate take: compared with OpenCV's decoder."""
    from mvtex.calibration.images import read_gray, read_image

    image = {"gray8": noise(30, 40, 1), "gray16": noise(30, 40, 1, np.uint16), "rgb8": noise(30, 40),
             "rgba8": noise(30, 40, 4), "rgb16": noise(30, 40, 3, np.uint16), "jpeg": noise(30, 40)}[kind]
    path = tmp_path / ("x.jpg" if kind == "jpeg" else "x.png")
    cv2.imwrite(str(path), image)
    stored = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    got = read_image(path)
    expected = stored if stored.ndim == 2 else stored[..., [2, 1, 0, 3][:stored.shape[2]]]
    assert got.dtype == expected.dtype
    if kind == "jpeg":  # two JPEG decoders may round differently
        assert np.abs(got.astype(int) - expected.astype(int)).max() <= 2
    else:
        np.testing.assert_array_equal(got, expected)
    gray = read_gray(path)
    assert gray.dtype == np.uint8
    assert np.abs(gray.astype(int) - cv2.imread(str(path), cv2.IMREAD_GRAYSCALE).astype(int)).max() <= 2
