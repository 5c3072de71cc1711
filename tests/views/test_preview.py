"""Stereo previews: eye geometry against OpenCV, scores against closed forms, the command
end to end on the wavy sheet."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import held_elsewhere, run

from mvtex.data.rig import builtin_rig_file, load_rig
from mvtex.views.cameras import interpolate_camera
from mvtex.views.preview import anaglyph, convergence, eye_cameras, garment_box, image_scores


def test_eyes_are_ipd_apart_and_see_the_expected_disparity():
    import cv2

    rig = load_rig(builtin_rig_file("stereo"))
    view = interpolate_camera(rig, {"left": 0.5, "right": 0.5}, "v")
    left, right = eye_cameras(view, 0.064)
    assert np.linalg.norm(left.center - right.center) == pytest.approx(0.064, abs=1e-12)
    assert np.allclose((left.center + right.center) / 2, view.center, atol=1e-12)
    depth = 2.0
    point = view.center + depth * view.R[2]  # on the viewpoint's optical axis
    f, cx = view.K[0, 0], view.K[0, 2]
    for eye, sign in ((left, 1.0), (right, -1.0)):
        rvec, _ = cv2.Rodrigues(eye.R)
        pixel, _ = cv2.projectPoints(point[None], rvec, eye.t, eye.K, np.zeros(5))
        # The left eye sits ipd/2 to the left: the point appears f*(ipd/2)/depth right of centre.
        assert pixel[0, 0, 0] == pytest.approx(cx + sign * f * 0.032 / depth, abs=1e-6)


def test_scores_and_anaglyph_closed_forms():
    rng = np.random.default_rng(0)
    a = rng.integers(20, 200, (64, 80, 3)).astype(np.uint8)
    box = (slice(None), slice(None))
    ssim, psnr = image_scores(a, a + 5, box)  # constant offset 5: MSE 25
    assert psnr == pytest.approx(10 * np.log10(255 ** 2 / 25), abs=1e-9)
    assert image_scores(a, a, box)[0] == pytest.approx(1.0)
    ana = anaglyph(a, 255 - a)
    assert np.array_equal(ana[..., 0], a[..., 0]) and np.array_equal(ana[..., 1:], (255 - a)[..., 1:])
    bg = np.zeros((50, 60, 3), np.uint8) + np.array([40, 40, 46], np.uint8)
    fg = bg.copy()
    fg[10:20, 30:35] = 200
    rows, cols = garment_box([bg, fg], margin=2)
    assert (rows.start, rows.stop, cols.start, cols.stop) == (8, 22, 28, 37)


def test_the_anaglyph_converges_at_the_cloth():
    """A point at the cloth's centre, drawn where OpenCV projects it in each eye, lands on one
    column of the anaglyph in both its red (left eye) and cyan (right eye) channels."""
    import cv2

    rig = load_rig(builtin_rig_file("stereo"))
    view = interpolate_camera(rig, {"left": 0.4, "right": 0.6}, "v")
    cloth = view.center + 2.1 * view.R[2] + np.random.default_rng(0).normal(scale=0.05, size=(200, 3))
    centre = cloth.mean(axis=0)
    shift = convergence(view, 0.064, cloth)
    assert shift["depth_m"] == pytest.approx(float(view.R[2] @ (centre - view.center)), abs=1e-9)
    pictures = []
    for eye in eye_cameras(view, 0.064):
        pixel, _ = cv2.projectPoints(centre[None], cv2.Rodrigues(eye.R)[0], eye.t, eye.K, np.zeros(5))
        image = np.zeros((eye.height, eye.width, 3), np.uint8)
        u, v = pixel[0, 0]
        image[int(round(v)) - 2:int(round(v)) + 3] = np.exp(-0.5 * ((np.arange(eye.width) - u) / 1.5) ** 2)[:, None] * 250
        pictures.append(image)
    ana = anaglyph(*pictures, shift["shift_px"]).astype(float)
    cols = np.arange(ana.shape[1])
    row = int(round(cv2.projectPoints(centre[None], cv2.Rodrigues(view.R)[0], view.t, view.K, np.zeros(5))[0][0, 0, 1]))

    def centre_of(values):  # of the dot, not of the background the shift uncovers (40, 40, 46)
        w = np.maximum(values - 50, 0)
        return (w * cols).sum() / w.sum()

    assert abs(centre_of(ana[row, :, 0]) - centre_of(ana[row, :, 1])) < 0.2
    plain = anaglyph(*pictures).astype(float)  # without the shift they are the disparity apart
    gap = centre_of(plain[row, :, 0]) - centre_of(plain[row, :, 1])
    assert gap == pytest.approx(shift["shift_px"], abs=0.3) and shift["shift_px"] > 20


@pytest.mark.slow
@pytest.mark.parametrize("method", ["blend", "reconstruct"])
def test_preview_command(tmp_path, sheet_set, capsys, method):
    import imageio.v3 as iio

    dataset, rig_path, ts = sheet_set
    out = tmp_path / "prev"
    code, stdout, err = run(capsys, "preview", dataset, "--rig", rig_path, "--texcoords", ts, "--pose", 4,
                            "--out", out, "--method", method, "--ipd", 0.05, "--json", "--quiet",
                            *(["--path"] if method == "blend" else []))
    assert code == 0, err
    report = json.loads(stdout)
    assert report == json.loads((out / "preview.json").read_text())
    assert report["pose"] == 4 and report["convergence"]["shift_px"] > 0
    for eye in ("left", "right"):
        scores = report["eyes"][eye]
        assert set(scores["ssim"]) == {"inferred", "texcoords"} and set(scores["psnr"]) == {"inferred", "texcoords"}
        # Texture sliding makes the smooth sheet show the folded sheet's material.
        assert scores["ssim"]["texcoords"] > scores["ssim"]["inferred"]
    stereo = iio.imread(out / "stereo.png")
    assert stereo.shape == (120, 320, 3)
    assert iio.imread(out / "anaglyph.png").shape == (120, 160, 3)
    if method == "blend":
        assert iio.imread(out / "path.gif", index=None).shape[0] >= 6


def test_preview_bad_input(tmp_path, sheet_set, capsys):
    dataset, rig_path, ts = sheet_set
    taken = tmp_path / "taken"
    taken.mkdir()
    (taken / "mine.txt").write_text("not mvtex's")
    code, _, err = run(capsys, "preview", dataset, "--rig", rig_path, "--texcoords", ts, "--pose", 4, "--out", taken,
                       "--quiet")
    assert code == 2 and "mvtex did not write" in err and len(err.strip().splitlines()) == 1
    assert (taken / "mine.txt").read_text() == "not mvtex's"
    # One run at a time per output folder.
    from mvtex.util.output import claim_output

    with held_elsewhere(claim_output(tmp_path / "busy", "preview")):
        code, _, err = run(capsys, "preview", dataset, "--rig", rig_path, "--texcoords", ts, "--pose", 4, "--out",
                           tmp_path / "busy", "--quiet")
    assert code == 2 and "in use by pid" in err and len(err.strip().splitlines()) == 1
    code, _, err = run(capsys, "preview", dataset, "--rig", rig_path, "--texcoords", ts, "--pose", 3, "--out",
                       tmp_path / "p", "--quiet")
    assert code == 2 and "pose 3" in err and len(err.strip().splitlines()) == 1
    code, _, err = run(capsys, "preview", dataset, "--rig", rig_path, "--texcoords", ts, "--pose", 4, "--out",
                       tmp_path / "p", "--weights", "a=0.7,b=0.7", "--quiet")
    assert code == 2 and "sum to 1" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "p").exists()
