"""Multi-view geometry (no GL) against OpenCV, SciPy, pycolmap, closed forms and brute force."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mvtex.data.camera import look_at
from mvtex.data.rig import Rig


def random_rig(rng, count: int, skew: float = 0.0) -> Rig:
    """count cameras 2 m from the origin looking at it, focal 600-900 px, optional skew K[0,1]."""
    cams = []
    for i in range(count):
        az, el = rng.uniform(-0.6, 0.6), rng.uniform(-0.3, 0.3)
        center = 2.0 * np.array([np.sin(az) * np.cos(el), np.sin(el), np.cos(az) * np.cos(el)])
        cam = look_at(f"c{i}", center, rng.normal(scale=0.02, size=3), width=640, height=480,
                      focal=rng.uniform(600, 900))
        if skew:
            K = cam.K.copy()
            K[0, 1] = skew * rng.uniform(0.5, 1.5)
            cam = replace(cam, K=K)
        cams.append(cam)
    return Rig(tuple(cams))


def closed_form_pixels(cameras, X):
    """(N,C,2) pixels by the homogeneous matrix product K (R X + t), skew included."""
    out = []
    for cam in cameras:
        h = (np.asarray(X) @ cam.R.T + cam.t) @ cam.K.T
        out.append(h[:, :2] / h[:, 2:])
    return np.stack(out, axis=1)


def noisy_tracks(rng, cameras, count: int, noise_px: float):
    X = rng.uniform(-0.3, 0.3, size=(count, 3))
    pix = closed_form_pixels(cameras, X) + rng.normal(scale=noise_px, size=(count, len(cameras), 2))
    w = np.ones((count, len(cameras)))
    w[: count // 3, -1] = 0  # a third seen by one camera fewer
    return X, pix, w


def scipy_optimum(cameras, pixels, weights, start):
    """The least-squares point of one track by scipy.optimize.least_squares on the closed form."""
    from scipy.optimize import least_squares

    used = np.flatnonzero(weights)

    def residual(p):
        return (closed_form_pixels([cameras[c] for c in used], p[None])[0] - pixels[used]).ravel()

    return least_squares(residual, start, xtol=1e-15, ftol=1e-15, gtol=1e-15).x, residual


# -- projection --------------------------------------------------------------------------------

def test_project_points_matches_opencv_and_the_closed_form_with_skew():
    import cv2

    from mvtex.recon.geometry import project_points, reprojection_errors

    rng = np.random.default_rng(2)
    cams = list(random_rig(rng, 3))
    X = rng.uniform(-0.3, 0.3, size=(40, 3))
    pix, y = project_points(cams, X)
    for c, cam in enumerate(cams):
        ref, _ = cv2.projectPoints(X, cv2.Rodrigues(cam.R)[0], cam.t, cam.K, None)  # OpenCV ignores skew
        assert np.abs(pix[:, c] - ref[:, 0]).max() < 1e-9
        assert np.allclose(y[:, c], X @ cam.R.T + cam.t, atol=1e-12)
    skewed = list(random_rig(rng, 3, skew=25.0))
    assert np.abs(project_points(skewed, X)[0] - closed_form_pixels(skewed, X)).max() < 1e-9
    shifted = closed_form_pixels(skewed, X) + np.array([3.0, 4.0])
    assert np.allclose(reprojection_errors(skewed, X, shifted), 5.0, atol=1e-9)


def test_projection_jacobian_matches_finite_differences_with_skew():
    from mvtex.recon.geometry import camera_arrays, project_points, projection_jacobian

    rng = np.random.default_rng(4)
    cams = list(random_rig(rng, 3, skew=40.0))
    X = rng.uniform(-0.3, 0.3, size=(10, 3))
    K, R, _ = camera_arrays(cams)
    J = projection_jacobian(K, R, project_points(cams, X)[1])  # (N,C,2,3)
    h = 1e-6
    for axis in range(3):
        step = np.zeros(3)
        step[axis] = h
        numeric = (closed_form_pixels(cams, X + step) - closed_form_pixels(cams, X - step)) / (2 * h)
        assert np.abs(J[..., axis] - numeric).max() < 1e-4 * np.abs(numeric).max()


def test_in_image_against_pixel_centres():
    from mvtex.recon.geometry import in_image

    # A 4x3 image: pixel centres 0..3 by 0..2, edges half a pixel beyond them.
    pixels = np.array([[0, 0], [3, 2], [-0.49, 1], [-0.5, 1], [3.49, 0], [3.5, 0], [1, 2.6], [np.nan, 1]])
    assert in_image(pixels, 4, 3).tolist() == [True, True, True, False, True, False, False, False]
    assert in_image(pixels.reshape(2, 4, 2), 4, 3).shape == (2, 4)
    with pytest.raises(ValueError, match=r"pixels must have shape \(...,2\), got \(3,\)"):
        in_image(np.zeros(3), 4, 3)


# -- triangulation -----------------------------------------------------------------------------

def test_dlt_matches_opencv_and_truth_without_noise():
    import cv2

    from mvtex.recon.geometry import triangulate_dlt

    rng = np.random.default_rng(0)
    rig = random_rig(rng, 2)
    X = rng.uniform(-0.3, 0.3, size=(50, 3))
    pix = np.stack([cam.project(X)[0] for cam in rig], axis=1)
    ours = triangulate_dlt(list(rig), pix, np.ones((50, 2)))
    a, b = rig.cameras
    h = cv2.triangulatePoints(a.projection, b.projection, pix[:, 0].T.copy(), pix[:, 1].T.copy())  # 2xN
    ref = (h[:3] / h[3]).T
    assert np.abs(ours - X).max() < 1e-9
    assert np.abs(ours - ref).max() < 1e-8
    # With skew the DLT still returns the truth (the closed form makes the pixels).
    skewed = list(random_rig(rng, 3, skew=30.0))
    assert np.abs(triangulate_dlt(skewed, closed_form_pixels(skewed, X), np.ones((50, 3))) - X).max() < 1e-9


def test_refined_triangulation_matches_scipy_and_pycolmap_with_noise():
    """Noisy observations: Gauss-Newton reaches scipy's least-squares optimum of the same
    reprojection error; COLMAP's estimator (its own linear + refinement) lands next to it."""
    from mvtex.formats.colmap import triangulate_colmap
    from mvtex.recon.geometry import refine_points, reprojection_errors, triangulate_dlt

    rng = np.random.default_rng(1)
    cams = list(random_rig(rng, 4))
    X, pix, w = noisy_tracks(rng, cams, 30, 0.7)
    ours = refine_points(cams, triangulate_dlt(cams, pix, w), pix, w, iterations=10)
    for i in range(30):
        used = np.flatnonzero(w[i])
        ref, residual = scipy_optimum(cams, pix[i], w[i], X[i])
        assert np.linalg.norm(ours[i] - ref) < 1e-7
        # COLMAP minimises an angular error: a point within the noise of ours (~1-5 mm from
        # the truth here), never with a lower reprojection error than ours.
        colmap = triangulate_colmap([cams[c] for c in used], pix[i, used], max_error_px=10.0)
        assert colmap is not None
        assert np.linalg.norm(colmap - ours[i]) < 2e-3
        assert np.sum(residual(ours[i]) ** 2) <= np.sum(residual(colmap) ** 2) + 1e-9
        # Noise-free, all three are the truth.
        exact = np.stack([cams[c].project(X[i])[0] for c in used])
        assert np.linalg.norm(triangulate_colmap([cams[c] for c in used], exact) - X[i]) < 1e-7
        assert np.linalg.norm(triangulate_dlt([cams[c] for c in used], exact[None], np.ones((1, len(used))))[0] - X[i]) < 1e-9
    err = reprojection_errors(cams, ours, pix)
    assert np.all(err[w > 0] < 4)


def test_gauss_newton_with_skew_reaches_the_scipy_optimum():
    """Skewed cameras: the Jacobian must carry K[0,1], or Gauss-Newton stops beside the optimum."""
    from mvtex.recon.geometry import refine_points

    rng = np.random.default_rng(6)
    cams = list(random_rig(rng, 3, skew=60.0))
    X, pix, w = noisy_tracks(rng, cams, 20, 1.0)
    start = X + rng.normal(scale=0.01, size=X.shape)  # 1 cm off
    ours = refine_points(cams, start, pix, w, iterations=15)
    for i in range(len(X)):
        ref, _ = scipy_optimum(cams, pix[i], w[i], X[i])
        assert np.linalg.norm(ours[i] - ref) < 1e-8


def test_pycolmap_engine_agrees_with_mvtex_engine():
    """The same tracks through both engines: the same least-squares points (< 1e-6 m), and
    both at scipy's optimum."""
    from mvtex.formats.colmap import triangulate_tracks
    from mvtex.recon.geometry import triangulate_points

    rng = np.random.default_rng(7)
    cams = list(random_rig(rng, 5))
    X, pix, w = noisy_tracks(rng, cams, 200, 0.8)
    w[150:, :2] = 0  # some tracks of three views
    pix[w == 0] = np.nan  # unobserved pixels are never read
    colmap = triangulate_tracks(cams, pix, w)
    ours = triangulate_points(cams, pix, w, iterations=5)
    assert np.abs(colmap - ours).max() < 1e-6
    for i in (0, 99, 199):
        ref, _ = scipy_optimum(cams, np.nan_to_num(pix[i]), w[i], X[i])
        assert np.linalg.norm(colmap[i] - ref) < 1e-7


def test_least_disagreement_picks_the_consistent_candidate():
    from mvtex.recon.geometry import least_disagreement

    rng = np.random.default_rng(8)
    cams = list(random_rig(rng, 3))
    X = np.array([[0.05, -0.02, 0.1]])
    true_px = closed_form_pixels(cams, X)[0]
    candidates = np.repeat(true_px[None], 6, axis=0)
    for k in range(6):
        if k != 4:
            candidates[k, k % 3] += rng.uniform(15, 40, size=2)  # one camera sees another spot
    best, point = least_disagreement(cams, candidates)
    assert best == 4 and np.linalg.norm(point - X[0]) < 1e-9


# -- distances, errors ---------------------------------------------------------------------------

def test_surface_distance_matches_brute_force(sheet):
    import trimesh.triangles
    from helpers import wave

    from mvtex.recon.geometry import surface_distance

    faces, _, rest = sheet
    positions = wave(rest, 0.015, 0.3)
    rng = np.random.default_rng(9)
    points = positions[rng.choice(len(positions), 60)] + rng.normal(scale=0.01, size=(60, 3))
    ours = surface_distance(points, positions, faces)
    tris = positions[faces]
    brute = np.array([np.linalg.norm(trimesh.triangles.closest_point(tris, np.repeat(p[None], len(tris), 0)) - p,
                                     axis=1).min() for p in points])
    assert np.abs(ours - brute).max() < 1e-12


def test_rmse_closed_form():
    from mvtex.recon.geometry import rmse

    a = np.zeros((4, 3))
    b = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [1.0, 2.0, 2.0]])
    assert rmse(a, b) == pytest.approx(np.sqrt((25 + 1 + 0 + 9) / 4))
    assert rmse(a, b, np.array([True, False, False, True])) == pytest.approx(np.sqrt(17))
    assert rmse(a, b, np.zeros(4, bool)) is None
    assert rmse(np.stack([a, a]), np.stack([b, a])) == pytest.approx(np.sqrt(35 / 8))  # (K,n,3) poses


# -- input checks -----------------------------------------------------------------------------

def test_shape_checks_name_the_argument_and_echo_the_shape():
    from mvtex.formats.colmap import triangulate_tracks
    from mvtex.recon.geometry import project_points, refine_points, reprojection_errors, rmse, triangulate_dlt
    from mvtex.util.checks import check_shape

    cams = list(random_rig(np.random.default_rng(0), 3))
    with pytest.raises(ValueError, match=r"pixels must have shape \(N,3,2\), got \(5, 2, 2\)"):
        triangulate_dlt(cams, np.zeros((5, 2, 2)), np.ones((5, 2)))
    with pytest.raises(ValueError, match=r"weights must have shape \(N,3\) with N=5, got \(4, 3\)"):
        triangulate_dlt(cams, np.zeros((5, 3, 2)), np.ones((4, 3)))
    with pytest.raises(ValueError, match=r"points must have shape \(N,3\) with N=5, got \(5, 2\)"):
        refine_points(cams, np.zeros((5, 2)), np.zeros((5, 3, 2)), np.ones((5, 3)))
    with pytest.raises(ValueError, match=r"points must have shape \(N,3\), got \(3,\)"):
        project_points(cams, np.zeros(3))
    with pytest.raises(ValueError, match=r"pixels must have shape \(N,3,2\) with N=2, got \(2, 3\)"):
        reprojection_errors(cams, np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"weights must have shape \(N,3\) with N=2, got \(2, 2\)"):
        triangulate_tracks(cams, np.zeros((2, 3, 2)), np.ones((2, 2)))
    with pytest.raises(ValueError, match=r"a and b must have one shape"):
        rmse(np.zeros((4, 3)), np.zeros((5, 3)))
    assert check_shape(np.zeros((2, 7, 3)), "x", ("K", "n", 3)) == {"K": 2, "n": 7}
