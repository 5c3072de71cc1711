"""Pictures for people: the shaded render against a Lambert term computed in NumPy, the
zoom camera against OpenCV's projection, colour scales fitted to the data, legends and
colour bars in the pictures the commands write."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import run

from mvtex.data.camera import look_at


def _plane(normal, centre=(0.0, 0.0, 0.0), size=0.6):
    """Two triangles: a square of side `size` through `centre`, perpendicular to `normal`."""
    n = np.asarray(normal, np.float64)
    n /= np.linalg.norm(n)
    a = np.cross(n, [0.0, 1.0, 0.0] if abs(n[1]) < 0.9 else [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    c = np.asarray(centre, np.float64)
    h = size / 2
    positions = np.array([c - h * a - h * b, c + h * a - h * b, c + h * a + h * b, c - h * a + h * b])
    return positions, np.array([[0, 1, 2], [0, 2, 3]])


@pytest.mark.gl
@pytest.mark.parametrize("normal", [(0.0, 0.0, 1.0), (0.5, 0.3, 1.0), (-0.7, -0.2, 0.6), (0.9, 0.6, 0.2)])
def test_shaded_render_is_the_lambert_term_of_the_face_normal(gl, normal):
    from mvtex.render.shading import CLOTH_RGB, KEY_LIGHT, SHADED_AMBIENT, SHADED_DIFFUSE, render_shaded

    camera = look_at("c", (0.0, 0.0, 2.0), (0, 0, 0), width=96, height=80, focal=120.0)
    positions, faces = _plane(normal)
    image = render_shaded(gl, positions, faces, camera, normals="face", supersample=1).astype(np.float64)
    # Independently: the face normal in camera coordinates, turned toward the camera.
    n = np.cross(positions[1] - positions[0], positions[2] - positions[0])
    n = camera.R @ (n / np.linalg.norm(n))
    centre_cam = camera.to_camera(positions.mean(axis=0))
    if n @ -centre_cam < 0:
        n = -n
    light = np.asarray(KEY_LIGHT) / np.linalg.norm(KEY_LIGHT)
    expected = np.asarray(CLOTH_RGB) * (SHADED_AMBIENT + SHADED_DIFFUSE * max(0.0, float(n @ light)))
    centre_px = np.round(camera.project(positions.mean(axis=0))[0]).astype(int)
    assert np.allclose(image[centre_px[1], centre_px[0]], expected, atol=1.5)


@pytest.mark.gl
def test_shaded_render_turns_the_normal_toward_the_camera_and_lights_folds_differently(gl):
    from mvtex.render.shading import render_shaded

    camera = look_at("c", (0.0, 0.0, 2.0), (0, 0, 0), width=64, height=64, focal=100.0)
    positions, faces = _plane((0.3, -0.4, 1.0))
    front = render_shaded(gl, positions, faces, camera, normals="face", supersample=1)
    back = render_shaded(gl, positions, faces[:, ::-1], camera, normals="face", supersample=1)
    assert np.array_equal(front, back)  # both sides lit the same
    other = render_shaded(gl, *_plane((-0.3, 0.4, 1.0)), camera, normals="face", supersample=1)
    assert abs(int(front[32, 32].sum()) - int(other[32, 32].sum())) > 60  # tilts toward/away from the light


def test_scaled_camera_is_the_crop_of_the_full_image():
    import cv2

    from mvtex.render.shading import scaled_camera

    camera = look_at("c", (0.3, 0.1, 2.0), (0, 0, 0), width=200, height=150, focal=240.0)
    box = (40.5, 20.5, 120.5, 80.5)
    zoom = scaled_camera(camera, box, 320, 240)
    points = np.random.default_rng(0).uniform(-0.2, 0.2, (20, 3))
    full, _ = cv2.projectPoints(points, cv2.Rodrigues(camera.R)[0], camera.t, camera.K, None)
    crop, _ = cv2.projectPoints(points, cv2.Rodrigues(zoom.R)[0], zoom.t, zoom.K, None)
    # The box's left/top edge (u0, v0) becomes the new image's edge at -0.5, and distances
    # from it grow by the zoom: u' = s (u - u0) - 0.5.
    expected = (full[:, 0] - np.array(box[:2])) * (320 / 80) - 0.5
    assert np.allclose(crop[:, 0], expected, atol=1e-9)


def test_fit_scale_top_is_the_99th_percentile_rounded_up():
    from mvtex.render.pictures import fit_scale

    rng = np.random.default_rng(1)
    a, b = rng.gamma(2.0, 0.003, 5000), rng.gamma(2.0, 0.0002, 5000)
    scale = fit_scale([a, np.r_[b, np.nan]], title="material error", unit="mm", factor=1e3)
    p99 = np.percentile(np.r_[a, b], 99)
    assert p99 <= scale.vmax <= 1.2 * p99
    assert scale.log and 10 ** -3 * scale.vmax <= scale.vmin <= 0.1 * scale.vmax
    assert scale.axis == "material error (mm)"
    colors = scale.colors(np.array([0.0, scale.vmin, scale.vmax, 10 * scale.vmax]))
    assert np.array_equal(colors[0], colors[1]) and np.array_equal(colors[2], colors[3])  # clipped at both ends
    linear = fit_scale(a, log=False)
    assert linear.vmin == 0 and np.percentile(a, 99) <= linear.vmax <= 1.2 * np.percentile(a, 99)


def test_colorbar_and_legend_draw_their_colours():
    from mvtex.render.pictures import ColorScale, colorbar, legend

    scale = ColorScale(1e-4, 2e-2, True, title="distance to gt", unit="mm", factor=1e3)
    bar = colorbar(300, scale, width=110)
    column = bar[:, 10].astype(int)
    top, bottom = scale.colors(np.array([scale.vmax, scale.vmin]))
    assert np.abs(column[12] - top).max() < 30 and np.abs(column[-12] - bottom).max() < 30
    assert (bar[:, 80:] > 200).any()  # the axis name is written along the right edge
    magenta = (255, 0, 255)
    picture = legend([(magenta, "another UV chart"), ((10, 200, 10), "triangulated")], 300)
    assert (picture == magenta).all(axis=2).sum() > 50 and (picture == (10, 200, 10)).all(axis=2).sum() > 50


@pytest.mark.gl
def test_eval_heatmaps_have_a_legend_for_magenta_and_fitted_scales(tmp_path, sheet_set, capsys):
    from mvtex.evaluation.uv import CHART_BOUNDARY_COLOR

    dataset, rig, tc = sheet_set
    code, _, err = run(capsys, "eval", dataset, "--rig", rig, "--texcoords", tc, "--poses", "0", "--heatmaps",
                       tmp_path / "heat", "--quiet")
    assert code == 0, err
    import imageio.v3 as iio

    picture = iio.imread(tmp_path / "heat" / "pose_00000_a.png")
    # The legend's magenta swatch sits below the heatmaps (the sheet has one chart: the
    # heatmaps themselves hold no magenta).
    rows = np.flatnonzero((picture == CHART_BOUNDARY_COLOR).all(axis=2).any(axis=1))
    assert rows.size and rows.min() > 2 * 120
    # Fitted scales: the texcoords' panel is not one flat colour.
    panel = picture[30:120, 164:324].reshape(-1, 3)
    assert len(np.unique(panel, axis=0)) > 20


@pytest.mark.gl
def test_render_writes_shaded_pictures(tmp_path, tiny_dataset, rig_file, gl, capsys, front_rig):
    from mvtex.data.dataset import load_dataset
    from mvtex.render.shading import render_shaded

    code, _, err = run(capsys, "render", tiny_dataset, "--rig", rig_file, "--pose", 1, "--out", tmp_path / "r",
                       "--quiet")
    assert code == 0, err
    import imageio.v3 as iio

    ds = load_dataset(tiny_dataset)
    for what, x in (("gt", ds.gt[1]), ("inferred", ds.inferred[1])):
        image = iio.imread(tmp_path / "r" / "a" / f"{what}_shaded.png")
        assert np.array_equal(image, render_shaded(gl, np.asarray(x), ds.faces, front_rig["a"]))
    assert iio.imread(tmp_path / "r" / "a" / "shaded_zoom.png").shape[1] > 2 * 160
    files = json.loads((tmp_path / "r" / "render.json").read_text())["files"]
    assert "a/gt_shaded.png" in files and "b/shaded_zoom.png" in files


@pytest.mark.gl
def test_comparison_picture_has_shaded_rows_colour_bars_and_legend(gl, tiny_dataset, front_rig):
    from mvtex.data.dataset import load_dataset
    from mvtex.render.pictures import TRIANGULATED_RGB, comparison_picture, comparison_scales

    ds = load_dataset(tiny_dataset)
    gt, inferred = np.asarray(ds.gt[2], np.float64), np.asarray(ds.inferred[2], np.float64)
    rec = gt + 0.2 * (inferred - gt)
    scales = comparison_scales(ds.faces, gt, inferred, rec, ds.rest)
    errors = np.r_[np.linalg.norm(inferred - gt, axis=1), np.linalg.norm(rec - gt, axis=1)]
    assert np.percentile(errors, 99) <= scales["error"].vmax <= 1.2 * np.percentile(errors, 99)
    triangulated = np.zeros(len(gt), bool)
    triangulated[::2] = True
    picture = comparison_picture(front_rig["a"], ds.faces, ds.uv, gt, inferred, rec, ds.rest, scales=scales,
                                 triangulated=triangulated, ctx=gl)
    assert picture.shape[0] > 5 * 120  # texture, geometry, zoom, strain, distance, legend
    legend_part = picture[5 * 124:]
    assert (legend_part == TRIANGULATED_RGB).all(axis=2).sum() > 30


def test_garments_frame_fits_the_row_of_garments():
    from mvtex.apps.report import garments_frame

    a = np.random.default_rng(2).uniform([-0.3, -0.4, -0.1], [0.3, 0.4, 0.1], (500, 3))
    frame = garments_frame([a, a, a], spacing=1.25, fov_deg=30.0, aspect=2.0)
    row = 2 * 1.25 * np.ptp(a[:, 0]) + np.ptp(a[:, 0])
    half = np.radians(15.0)
    # The row fits the width and the garment the height, with 10 % to spare at most.
    assert frame["radius"] * np.tan(half) * 2.0 * 2 >= row
    assert frame["radius"] * np.tan(half) * 2 >= np.ptp(a[:, 1])
    assert frame["radius"] <= 1.1 * max(row / (2 * 2.0 * np.tan(half)), np.ptp(a[:, 1]) / (2 * np.tan(half))) + 1e-9
