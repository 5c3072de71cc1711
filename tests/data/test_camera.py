"""Cameras and rigs: projection against OpenCV, YAML and COLMAP round trips."""

from __future__ import annotations

import numpy as np
import pytest

from mvtex.data.camera import Camera, look_at
from mvtex.data.rig import Rig, builtin_rig_file, load_rig, save_rig
from mvtex.util.errors import InputError


def random_camera(rng, name="c") -> Camera:
    import cv2

    rvec = rng.normal(size=3) * 0.3
    R = cv2.Rodrigues(rvec)[0]
    K = np.array([[rng.uniform(300, 900), 0, rng.uniform(100, 200)], [0, rng.uniform(300, 900), rng.uniform(80, 160)], [0, 0, 1]])
    return Camera(name, 320, 240, K=K, R=R, t=np.array([0.1, -0.05, 2.0]) + rng.normal(size=3) * 0.05)


def test_project_matches_opencv():
    import cv2

    rng = np.random.default_rng(1)
    cam = random_camera(rng)
    X = rng.uniform(-0.4, 0.4, size=(200, 3))
    ours, depth = cam.project(X)
    ref, _ = cv2.projectPoints(X, cv2.Rodrigues(cam.R)[0], cam.t, cam.K, None)
    assert np.abs(ours - ref.reshape(-1, 2)).max() < 1e-9
    assert np.allclose(depth, (X @ cam.R.T + cam.t)[:, 2])


def test_center_and_rays_hit_points():
    rng = np.random.default_rng(2)
    cam = random_camera(rng)
    X = rng.uniform(-0.4, 0.4, size=(50, 3))
    pix, depth = cam.project(X)
    rays = cam.pixel_rays(pix)
    # The point lies on the ray from the centre through its pixel.
    along = np.einsum("ij,ij->i", X - cam.center, rays)
    assert np.abs(cam.center + along[:, None] * rays - X).max() < 1e-9


def test_look_at_puts_target_at_principal_point():
    cam = look_at("c", (0.5, 0.4, 2.0), (0.0, 0.1, 0.0), width=512, height=512, focal=1000)
    pix, depth = cam.project(np.array([0.0, 0.1, 0.0]))
    assert np.allclose(pix, [255.5, 255.5]) and depth > 0
    up, _ = cam.project(np.array([0.0, 0.3, 0.0]))
    assert up[1] < pix[1]  # world up appears higher in the image (smaller v)
    assert np.allclose(cam.R @ cam.R.T, np.eye(3))


def test_rig_yaml_round_trip_is_lossless(tmp_path):
    rng = np.random.default_rng(3)
    cams = [random_camera(rng, f"cam{i}") for i in range(3)]
    cams[1] = Camera("cam1", 320, 240, K=cams[1].K, R=cams[1].R, t=cams[1].t, dist=[0.1, -0.01, 1e-3, 2e-4, 0.003])
    rig = Rig(tuple(cams))
    save_rig(rig, tmp_path / "rig.yaml")
    back = load_rig(tmp_path / "rig.yaml")
    assert back.names == rig.names
    for a, b in zip(rig, back):
        assert (a.width, a.height) == (b.width, b.height)
        for key in ("K", "R", "t", "dist"):
            assert np.array_equal(getattr(a, key), getattr(b, key)), key


def test_builtin_rigs_frame_the_origin():
    for name, count in (("stereo", 2), ("square4", 4), ("trapezoid12", 12)):
        rig = load_rig(builtin_rig_file(name))
        assert len(rig) == count
        for cam in rig:
            pix, depth = cam.project(np.zeros(3))
            assert depth > 1.5 and 0 <= pix[0] < cam.width and 0 <= pix[1] < cam.height
    stereo = load_rig(builtin_rig_file("stereo"))
    a, b = (cam.center / np.linalg.norm(cam.center) for cam in stereo)
    assert 25 < np.degrees(np.arccos(a @ b)) < 35


def test_colmap_round_trip_and_pixel_convention(tmp_path):
    import pycolmap

    from mvtex.formats.colmap import read_rig, rig_reconstruction, write_rig

    rig = load_rig(builtin_rig_file("square4"))
    write_rig(rig, tmp_path / "model")
    back = read_rig(tmp_path / "model")
    assert back.names == rig.names
    for a, b in zip(rig, back):
        assert np.abs(a.K - b.K).max() < 1e-12 and np.abs(a.R - b.R).max() < 1e-12 and np.abs(a.t - b.t).max() < 1e-12
    # pycolmap's own projection lands at our pixel + 0.5.
    rec = pycolmap.Reconstruction(str(tmp_path / "model"))
    X = np.array([[0.1, 0.05, 0.02], [-0.2, 0.3, -0.1]])
    by_name = {im.name: im for im in rec.images.values()}
    for cam in rig:
        image = by_name[f"{cam.name}.png"]
        for x in X:
            assert np.abs(np.asarray(image.project_point(x)) - (cam.project(x)[0] + 0.5)).max() < 1e-9
    rec2, ids = rig_reconstruction(rig)
    assert set(ids) == set(rig.names)


@pytest.mark.parametrize("text,problem", [
    ("not: [valid", "malformed"),
    ("%YAML:1.0\nformat: other\n", "not an mvtex rig"),
    ('%YAML:1.0\nformat: "mvtex-rig"\nversion: 1\n', "cameras"),
])
def test_bad_rig_files_name_the_file(tmp_path, text, problem):
    path = tmp_path / "rig.yaml"
    path.write_text(text)
    with pytest.raises(InputError) as info:
        load_rig(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_missing_rig_file(tmp_path):
    with pytest.raises(InputError, match="not found"):
        load_rig(tmp_path / "nope.yaml")


@pytest.mark.slow
@pytest.mark.parametrize("name", ["stereo", "square4"])
def test_every_truncation_of_a_rig_file_loads_or_names_the_file(tmp_path, name):
    """A rig file cut anywhere (a copy interrupted) is read or refused in one line, never an OpenCV assertion."""
    text = builtin_rig_file(name).read_text()
    path = tmp_path / "rig.yaml"
    refused = 0
    for end in range(0, len(text), 7):
        path.write_text(text[:end])
        try:
            load_rig(path)
        except InputError as err:
            assert str(err).startswith(f"{path}: ") and "\n" not in str(err)
            refused += 1
    assert refused > len(text) // 14
