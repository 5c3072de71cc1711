"""Which observations the reconstruction trusts: the triangle test against a closed form,
the cameras' vote against pycolmap's RANSAC triangulation, and planted wrong observations
(a triangle with swapped texcoords, a shifted camera) rejected end to end, the points
checked against pycolmap's triangulation of the clean tracks."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import grid_mesh, wave

from mvtex.data.camera import look_at
from mvtex.data.rig import Rig


def square_rig(width: int = 200, height: int = 160) -> Rig:
    """Four cameras on a 0.5 m square, 1.2 m in front of the sheet (a small `square4`)."""
    cams = []
    for name, (x, y) in (("tl", (-0.25, 0.25)), ("tr", (0.25, 0.25)), ("bl", (-0.25, -0.25)), ("br", (0.25, -0.25))):
        cams.append(look_at(name, (x, y, 1.2), (0, 0, 0), width=width, height=height, focal=260.0))
    return Rig(tuple(cams))


def hypotheses_of(vertex, camera, pixel):
    from mvtex.recon.locate import Hypotheses

    vertex, camera = np.asarray(vertex, np.int64), np.asarray(camera, np.int64)
    return Hypotheses(vertex, camera, np.asarray(pixel, np.float64), np.zeros(len(vertex), np.int64),
                      np.full((len(vertex), 3), 1 / 3))


# -- the triangle test -----------------------------------------------------------------------------

def test_triangle_stretch_closed_form():
    from mvtex.recon.consensus import screen_hypotheses, triangle_stretch

    faces = np.array([[0, 1, 2], [1, 3, 2]])
    uv = np.array([[0.0, 0.0], [0.1, 0.0], [0.0, 0.1], [0.1, 0.1]])
    T = uv.copy()
    T[3] = [0.4, 0.1]  # edge 1-3 grows from 0.1 to sqrt(0.3² + 0.1²), edge 3-2 from 0.1 to 0.4
    stretch = triangle_stretch(faces, uv, T, np.array([0, 1]))
    assert stretch[0] == pytest.approx(1.0)
    assert stretch[1] == pytest.approx(4.0)
    # A uniform scale of T_N by s is a stretch s on every edge.
    assert np.allclose(triangle_stretch(faces, uv, 1.5 * uv, np.array([0, 1])), 1.5)
    hyp = hypotheses_of([5, 6, 7], [0, 0, 1], np.zeros((3, 2)))
    hyp = type(hyp)(hyp.vertex, hyp.camera, hyp.pixel, np.array([0, 1, 1]), hyp.bary)
    kept, dropped = screen_hypotheses(hyp, faces, uv, [T, uv], max_stretch=2.0)
    assert dropped == 1 and kept.vertex.tolist() == [5, 7]


# -- the vote ---------------------------------------------------------------------------------------

def test_vote_finds_the_inliers_pycolmap_ransac_finds():
    """Five cameras, 0.05 px noise; per point up to two cameras see another spot (5-30 px
    off), and some cameras hold a second, wrong hypothesis. The vote keeps exactly the true
    observations, like COLMAP's LO-RANSAC triangulation given every hypothesis, and lands
    on the same point."""
    import pycolmap

    from mvtex.formats.colmap import COLMAP_PIXEL_OFFSET, to_colmap_camera
    from mvtex.recon.consensus import vote
    from mvtex.recon.geometry import triangulate_points

    rng = np.random.default_rng(11)
    cams = []
    for i in range(5):
        az, el = rng.uniform(-0.6, 0.6), rng.uniform(-0.3, 0.3)
        centre = 2.0 * np.array([np.sin(az) * np.cos(el), np.sin(el), np.cos(az) * np.cos(el)])
        cams.append(look_at(f"c{i}", centre, (0, 0, 0), width=640, height=480, focal=800.0))
    N = 40
    X = rng.uniform(-0.2, 0.2, size=(N, 3))
    V, Cm, P, truth = [], [], [], []
    for i in range(N):
        wrong = set(rng.choice(5, size=int(rng.integers(0, 3)), replace=False).tolist())
        for c, cam in enumerate(cams):
            px = cam.project(X[i])[0] + rng.normal(scale=0.05, size=2)
            if c in wrong:
                px = px + rng.uniform(5, 30, size=2) * rng.choice([-1, 1], size=2)
            V.append(i), Cm.append(c), P.append(px), truth.append(c not in wrong)
            if rng.uniform() < 0.3:  # a second hypothesis, elsewhere
                V.append(i), Cm.append(c), P.append(px + rng.uniform(8, 40, size=2)), truth.append(False)
    V, Cm, P, truth = map(np.asarray, (V, Cm, P, truth))
    result = vote(hypotheses_of(V, Cm, P), N, cams, threshold_px=1.0)

    used = result.weights > 0
    expected = np.zeros((N, 5), bool)
    expected[V[truth], Cm[truth]] = True
    assert np.array_equal(used, expected)
    assert np.array_equal(result.pixels[used], P[truth][np.lexsort((Cm[truth], V[truth]))])
    assert result.counts["disagreement"] + result.counts["alternative"] == int((~truth).sum())
    clean = triangulate_points(cams, np.where(expected[..., None], result.pixels, np.nan), expected.astype(float))
    assert np.abs(result.points - clean).max() < 1e-9
    options = pycolmap.EstimateTriangulationOptions()
    options.residual_type = pycolmap.TriangulationResidualType.REPROJECTION_ERROR
    options.ransac.max_error = 1.0
    options.ransac.random_seed = 0
    poses = [pycolmap.Rigid3d(pycolmap.Rotation3d(c.R), c.t) for c in cams]
    colmap_cams = [to_colmap_camera(c, k + 1) for k, c in enumerate(cams)]
    for i in range(N):
        rows = np.flatnonzero(V == i)
        found = pycolmap.estimate_triangulation(P[rows] + COLMAP_PIXEL_OFFSET, [poses[c] for c in Cm[rows]],
                                                [colmap_cams[c] for c in Cm[rows]], options)
        assert found is not None
        assert np.array_equal(np.asarray(found["inliers"], bool), truth[rows])
        # COLMAP refines an angular error, the vote the reprojection error: ~0.1 mm apart.
        assert np.linalg.norm(np.asarray(found["xyz"]).ravel() - result.points[i]) < 3e-4
        assert np.linalg.norm(result.points[i] - X[i]) < 1e-3


def test_vote_with_two_cameras_needs_agreement():
    """Two cameras cannot vote one out: a pair that disagrees across the epipolar line is
    not triangulated, one that agrees is."""
    from mvtex.recon.consensus import vote

    cams = [look_at(n, (x, 0.0, 2.0), (0, 0, 0), width=640, height=480, focal=800.0)
            for n, x in (("l", -0.5), ("r", 0.5))]
    X = np.array([[0.0, 0.0, 0.0], [0.05, 0.1, 0.0]])
    px = np.stack([[c.project(x)[0] for c in cams] for x in X])  # (2,2,2)
    px[1, 1, 1] += 4.0  # vertical: off the epipolar line of a horizontal pair
    result = vote(hypotheses_of([0, 0, 1, 1], [0, 1, 0, 1], px.reshape(-1, 2)), 2, cams, threshold_px=0.5)
    assert result.weights.tolist() == [[1.0, 1.0], [0.0, 0.0]]
    assert np.linalg.norm(result.points[0] - X[0]) < 1e-9 and np.all(np.isnan(result.points[1]))
    assert result.counts["disagreement"] == 2


# -- planted observations, end to end ----------------------------------------------------------------

@pytest.fixture(scope="module")
def planted(gl):
    """A wavy sheet seen by four cameras, inferred = gt, and three sets of texcoords: the
    clean ones (T_N = T_G); "dirty" ones with one triangle of camera tr whose two corners'
    texcoords are swapped and, in camera bl, a band of columns whose T_N jumps by 0.06 in u
    (a fold edge on each side of it); and "shifted" ones, camera br's texcoords moved by
    0.01 in u (about 1.3 px). The two kinds are planted in separate runs: where the swapped
    triangle leaves a vertex two exact cameras, a shifted third one that agrees with them
    within the vote's threshold cannot be told from them (no vote can)."""
    from mvtex.recon.triangulate import reconstruct

    faces, uv, rest = grid_mesh(40, 34)
    uv = uv.astype(np.float64)
    gt = wave(rest, 0.015, 0.4)
    rig = square_rig()
    clean_T = {c.name: uv.copy() for c in rig}
    T = {c.name: uv.copy() for c in rig}
    tri = faces[16 * 39 + 20]  # the first triangle of cell (row 16, column 20), inside the sheet
    a, b = tri[0], tri[1]
    T["tr"][[a, b]] = T["tr"][[b, a]]
    band = (uv[:, 0] > 0.6) & (uv[:, 0] < 0.7)
    T["bl"][band, 0] += 0.06
    shifted_T = {c.name: uv.copy() for c in rig}
    shifted_T["br"][:, 0] += 0.01  # ~ 6 mm on the sheet: ~1.3 px
    clean = reconstruct(uv, gt, faces, uv, clean_T, rig, ctx=gl)
    dirty = reconstruct(uv, gt, faces, uv, T, rig, ctx=gl)
    shifted = reconstruct(uv, gt, faces, uv, shifted_T, rig, ctx=gl)
    return dict(faces=faces, uv=uv, gt=gt, rig=rig, T=T, tri=tri, band=band, clean=clean, dirty=dirty,
                shifted=shifted)


def _clean_tracks_by_colmap(rig, gt, rec):
    """pycolmap's triangulation (multi-view point + points-only BA) of the gt vertices'
    exact projections into the cameras `rec` used for each."""
    from mvtex.formats.colmap import triangulate_tracks

    names = list(rig.names)
    used = np.stack([np.isfinite(rec.observations[c][:, 0]) for c in names], axis=1)
    rows = np.flatnonzero(rec.triangulated)
    pixels = np.stack([rig[c].project(gt[rows])[0] for c in names], axis=1)
    return rows, triangulate_tracks(list(rig), pixels, used[rows].astype(float))


@pytest.mark.slow
def test_planted_observations_are_rejected(planted):
    clean, dirty, shifted, rig = planted["clean"], planted["dirty"], planted["shifted"], planted["rig"]
    # The shifted camera disagrees with the other three wherever two of them see a vertex.
    br = np.isfinite(shifted.observations["br"][:, 0])
    others = np.sum([np.isfinite(clean.observations[c][:, 0]) for c in ("tl", "tr", "bl")], axis=0)
    assert (others >= 2).sum() > 1000
    assert br[others >= 2].sum() == 0
    assert shifted.rejected_observations["disagreement"] >= 0.9 * np.isfinite(clean.observations["br"][:, 0]).sum()
    assert shifted.triangulated.sum() >= 0.97 * clean.triangulated.sum()
    # Camera tr's swapped triangle: T_G of each swapped corner is now found at the other
    # corner, a wrong pixel; neither is used. The triangles around the two corners are
    # distorted too, so tr may lose a vertex of theirs, but no other (every T_G outside
    # them is still found at its own vertex), and no wrong pixel is used.
    tr_used = dirty.observations["tr"]
    expect = rig["tr"].project(planted["gt"])[0]
    seen = np.isfinite(tr_used[:, 0])
    assert np.abs(tr_used[seen] - expect[seen]).max() < 1e-6
    lost = np.flatnonzero(np.isfinite(clean.observations["tr"][:, 0]) & ~seen)
    swapped = planted["tri"][:2]
    faces = planted["faces"]
    ring = np.unique(faces[np.any(np.isin(faces, swapped), axis=1)])
    assert set(swapped.tolist()) <= set(lost.tolist()) <= set(ring.tolist())
    assert np.all(dirty.triangulated[lost])  # from the other cameras
    # Camera bl's fold edges: T_N of the triangles across them interpolates between material
    # 0.06 apart; what is located there is dropped by the triangle test, the rest by the vote.
    bl_used = dirty.observations["bl"]
    seen = np.isfinite(bl_used[:, 0])
    assert np.abs(bl_used[seen] - rig["bl"].project(planted["gt"])[0][seen]).max() < 1e-6
    assert dirty.rejected_observations["stretched_triangle"] > 20
    assert clean.rejected_observations["disagreement"] == 0 and clean.rejected_observations["stretched_triangle"] == 0
    # Nearly every vertex is still triangulated, from the three good cameras.
    assert dirty.triangulated.sum() >= 0.97 * clean.triangulated.sum()


def test_planted_points_land_within_the_clean_error(planted):
    """Every point of the planted run is as close to pycolmap's triangulation of its clean
    track as the clean run's points are (both are exact here: observations are exact
    projections), and as close to gt."""
    gt, rig, clean = planted["gt"], planted["rig"], planted["clean"]
    rows, colmap = _clean_tracks_by_colmap(rig, gt, clean)
    clean_error = np.abs(clean.points[rows] - colmap).max()
    assert clean_error < 1e-6
    for planted_run in (planted["dirty"], planted["shifted"]):
        rows, colmap = _clean_tracks_by_colmap(rig, gt, planted_run)
        assert np.abs(planted_run.points[rows] - colmap).max() <= clean_error + 1e-9
        tri = planted_run.triangulated
        assert np.abs(planted_run.points[tri] - gt[tri]).max() <= np.abs(clean.points[clean.triangulated] -
                                                                       gt[clean.triangulated]).max() + 1e-9


def test_every_hypothesis_is_accounted_for(planted):
    for rec in (planted["clean"], planted["dirty"], planted["shifted"]):
        assert set(rec.rejected_observations) == {"unassigned", "duplicate", "occluded", "hidden_by_body",
                                                  "stretched_triangle", "fewer_than_2_views", "alternative",
                                                  "disagreement", "reprojection", "point_rejected"}
        used = sum(np.isfinite(o[:, 0]).sum() for o in rec.observations.values())
        assert used == rec.stats["used_observations"]
        assert rec.stats["hypotheses"] == used + sum(rec.rejected_observations.values())


def test_threshold_grows_with_the_noise_of_the_observations():
    """consensus_scale: the threshold is that many times the median reprojection error of
    the points triangulated from every observation (no outliers here, 0.3 px noise, so the
    loose vote keeps them all); with scale 0 it is consensus_px."""
    from mvtex.recon.geometry import reprojection_errors, triangulate_points
    from mvtex.recon.triangulate import ReconOptions, consensus_threshold

    rng = np.random.default_rng(4)
    cams = list(square_rig(640, 480))
    X = rng.uniform(-0.2, 0.2, size=(200, 3))
    px = np.stack([c.project(X)[0] for c in cams], axis=1) + rng.normal(scale=0.3, size=(200, 4, 2))
    V, Cm = np.meshgrid(np.arange(200), np.arange(4), indexing="ij")
    hyp = hypotheses_of(V.ravel(), Cm.ravel(), px.reshape(-1, 2))
    points = triangulate_points(cams, px, np.ones((200, 4)))
    expected = 3.0 * np.median(reprojection_errors(cams, points, px))
    assert expected > 0.5
    got = consensus_threshold(hyp, 200, cams, ReconOptions(consensus_px=0.5, consensus_scale=3.0))
    assert got == pytest.approx(expected, rel=1e-9)
    assert consensus_threshold(hyp, 200, cams, ReconOptions(consensus_px=0.5, consensus_scale=0.0)) == 0.5
    assert consensus_threshold(hyp, 200, cams, ReconOptions(consensus_px=5.0, consensus_scale=3.0)) == 5.0


def test_the_threshold_of_predicted_texcoords_grows_by_default():
    from mvtex.recon.triangulate import ReconOptions

    assert ReconOptions().for_source("tsnn").consensus_scale == 4.0
    assert ReconOptions().for_source("ts").consensus_scale == 0.0
    assert ReconOptions(consensus_scale=1.5).for_source("tsnn").consensus_scale == 1.5
