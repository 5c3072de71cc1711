"""Inputs that used to end in a traceback, through the public API and `mvtex.cli.main`:
cameras of different sizes in one rig, the largest and the smallest image sizes a rig may
declare, negative seeds, a network resolution below what its architecture halves down to.
Each works or is one typed error naming the argument."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest
from helpers import one_line_error, run

import mvtex
from mvtex.data.camera import MAX_IMAGE_SIZE


def resized(camera, width: int, height: int):
    """`camera` with another image size, the same field of view and centred principal point."""
    K = camera.K.copy()
    K[0, 0] *= width / camera.width
    K[1, 1] *= height / camera.height
    K[0, 2], K[1, 2] = (width - 1) / 2, (height - 1) / 2
    return replace(camera, width=width, height=height, K=K)


def test_a_rig_of_mixed_sizes_renders(tmp_path, tiny_dataset, front_rig, gl, capsys):
    a, b = front_rig.cameras
    rig = mvtex.Rig((a, resized(b, 80, 60)))
    summary = mvtex.render_pose(mvtex.load_dataset(tiny_dataset), rig, 0, tmp_path / "api", progress=False, ctx=gl)
    overview = cv2.imread(str(tmp_path / "api" / "overview.png"))
    assert overview.shape[:2] == (4 * 120 + 3 * 4, 2 * 160 + 4)  # cells as large as the largest picture (4 rows)
    small = cv2.imread(str(tmp_path / "api" / "b" / "gt.png"))
    assert small.shape[:2] == (60, 80) and "b/gt.png" in summary["files"]
    # The picture sits in its cell's corner: the overview there is the picture itself.
    assert np.array_equal(overview[30:60, 164:244], small[30:60, :80])
    mvtex.save_rig(rig, tmp_path / "mixed.yaml")
    code, _, err = run(capsys, "render", tiny_dataset, "--rig", tmp_path / "mixed.yaml", "--pose", 0, "--out",
                       tmp_path / "cli", "--quiet")
    assert code == 0, err


@pytest.mark.slow
@pytest.mark.parametrize("size", [(MAX_IMAGE_SIZE, 2), (2, MAX_IMAGE_SIZE), (1, 1)])
def test_the_largest_and_smallest_image_sizes_render_and_slide(size, tmp_path, tiny_dataset, front_rig, gl, capsys):
    width, height = size
    a, b = front_rig.cameras
    # Keep the sheet in view: scale the focal lengths with the image's larger side.
    rig = mvtex.Rig(tuple(resized(c, width, height) for c in (a, b)))
    if (width, height) == (1, 1):
        rig = mvtex.Rig(tuple(replace(c, K=np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1]])) for c in rig))
    ds = mvtex.load_dataset(tiny_dataset)
    mvtex.render_pose(ds, rig, 0, tmp_path / "render", progress=False, ctx=gl)
    image = cv2.imread(str(tmp_path / "render" / "a" / "gt.png"))
    assert image.shape[:2] == (height, width)
    mvtex.save_rig(rig, tmp_path / "rig.yaml")
    code, _, err = run(capsys, "slide", tiny_dataset, "--rig", tmp_path / "rig.yaml", "--poses", "0:2", "--subdiv", 0,
                       "--workers", 1, "--out", tmp_path / "ts", "--quiet")
    assert code == 0, err
    tc = mvtex.open_texcoords(tmp_path / "ts")
    assert tc.cameras == ["a", "b"] and np.all(np.isfinite(tc.displacement("a", 0)))


@pytest.mark.parametrize("seed", [-1, 2**32, 1.5, True])
def test_seeds_out_of_range_are_typed_errors(seed, tmp_path, capsys):
    for make in (lambda: mvtex.SynthOptions(num_poses=10, seed=seed), lambda: mvtex.DemoOptions(seed=seed),
                 lambda: mvtex.TrainOptions(seed=seed)):
        with pytest.raises(mvtex.OptionError, match="^seed must be an integer"):
            make()
    if isinstance(seed, int) and not isinstance(seed, bool):
        code, _, err = run(capsys, "synth", "--out", tmp_path / "ds", "--num-poses", 10, "--seed", seed, "--quiet")
        one_line_error(code, err, "--seed must be an integer in [0, 4294967295]")
        assert not (tmp_path / "ds").exists()


def test_a_unet_resolution_below_its_levels_is_a_typed_error(tmp_path, tiny_dataset, slid_sheet, capsys):
    with pytest.raises(mvtex.OptionError, match="^resolution must be at least 16 for the unet"):
        mvtex.TrainOptions(arch="unet", resolution=8)
    code, _, err = run(capsys, "train", tiny_dataset, "--texcoords", slid_sheet, "--arch", "unet", "--resolution", 8,
                       "--rig", slid_sheet.parent / "rig.yaml", "--out", tmp_path / "m", "--quiet")
    one_line_error(code, err, "--resolution must be at least 16")
    assert not (tmp_path / "m").exists()
