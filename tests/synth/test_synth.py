"""Properties of the built-in datasets (mvtex.synth.generate), measured independently.

Every quantity is recomputed here from the arrays (edges from faces, seams from equal
rest positions, normals from cross products, distances to the body from an exact
point-to-triangle search, insideness from ray casting), not read back from `stats` alone.
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers import mesh_distance

from mvtex.synth.generate import synthesize, write_synth
from mvtex.synth.options import MAX_POSES, SynthOptions
from mvtex.synth.predictor import fit_predictor
from mvtex.synth.shirt import POSE_DIM, deform, make_body, make_garment, pose_body, sample_poses

NUM_POSES = 48


@pytest.fixture(scope="module")
def data() -> dict:
    return synthesize(SynthOptions(num_poses=NUM_POSES, seed=0))


@pytest.fixture(scope="module")
def skirt() -> dict:
    return synthesize(SynthOptions(num_poses=NUM_POSES, seed=0, garment="skirt"))


def _edges(faces: np.ndarray) -> np.ndarray:
    """Unique undirected edges (e, 2) of a triangle list."""
    pairs = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    return np.unique(np.sort(pairs, axis=1), axis=0)


def _welded(rest: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(vertex -> welded point (n,), faces over welded points): seam copies joined."""
    _, inverse = np.unique(rest, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    return inverse, inverse[faces]


def _seam_groups(rest: np.ndarray) -> list[np.ndarray]:
    """Groups of vertex indices that share a rest position (more than one copy)."""
    _, inverse, counts = np.unique(rest, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    order = np.argsort(inverse, kind="stable")
    groups = np.split(order, np.cumsum(counts)[:-1])
    return [g for g in groups if len(g) > 1]


def _face_normals(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    p = positions.astype(np.float64)
    return np.cross(p[..., faces[:, 1], :] - p[..., faces[:, 0], :], p[..., faces[:, 2], :] - p[..., faces[:, 0], :])


def _boundary_loops(faces: np.ndarray) -> list[list[int]]:
    """Boundary edges (used by one face) chained into closed loops of vertex indices."""
    directed = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    key = np.sort(directed, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    border = directed[counts[inverse.reshape(-1)] == 1]
    following = dict(zip(border[:, 0].tolist(), border[:, 1].tolist()))
    assert len(following) == len(border), "a vertex starts two boundary edges (not a manifold border)"
    loops, seen = [], set()
    for start in following:
        if start in seen:
            continue
        loop, v = [], start
        while v not in seen:
            seen.add(v)
            loop.append(v)
            v = following[v]
        assert v == start
        loops.append(loop)
    return loops


@pytest.mark.slow
def test_shapes_dtypes_and_split(data):
    faces, uv, rest = data["faces"], data["uv"], data["rest"]
    n = len(rest)
    assert 3000 <= n <= 5000
    assert data["name"] == "shirt"
    assert faces.dtype == np.int32 and faces.ndim == 2 and faces.shape[1] == 3
    assert faces.min() == 0 and faces.max() == n - 1
    assert uv.dtype == np.float32 and uv.shape == (n, 2)
    assert rest.dtype == np.float32 and rest.shape == (n, 3)
    for key in ("gt", "inferred"):
        assert data[key].dtype == np.float32 and data[key].shape == (NUM_POSES, n, 3)
        assert np.isfinite(data[key]).all()
    body, body_faces = data["body"], data["body_faces"]
    assert body.dtype == np.float32 and body.shape[0] == NUM_POSES and body.shape[2] == 3 and np.isfinite(body).all()
    assert body_faces.dtype == np.int32 and body_faces.min() == 0 and body_faces.max() == body.shape[1] - 1
    assert len(body_faces) <= 5000  # rasterized in every job: lean
    poses = data["poses"]
    assert poses.dtype == np.float32 and poses.shape == (NUM_POSES, POSE_DIM)
    assert 8 <= POSE_DIM <= 16
    assert poses.min() >= -1.0 and poses.max() <= 1.0
    split = data["split"]
    assert sorted(split["train"] + split["val"] + split["test"]) == list(range(NUM_POSES))
    assert (len(split["train"]), len(split["val"]), len(split["test"])) == (38, 5, 5)
    stats = data["stats"]
    assert stats["num_vertices"] == n and stats["num_faces"] == len(faces)
    assert stats["body_num_vertices"] == body.shape[1] and stats["body_num_faces"] == len(body_faces)
    assert all(isinstance(v, float) for v in stats.values())


@pytest.mark.slow
def test_the_shirt_is_a_t_shirt_with_four_openings(data):
    rest, faces = data["rest"].astype(np.float64), data["faces"]
    lo, hi = rest.min(axis=0), rest.max(axis=0)
    assert np.all(np.abs((lo + hi) / 2) < 0.03)  # centred near the origin
    width, height, depth = hi - lo
    assert 0.6 <= height <= 0.7 and 0.65 <= width <= 0.85 and 0.2 <= depth <= 0.3  # sleeves out to the sides
    # Sewn on its seams it is one closed surface with four holes: a manifold with
    # Euler characteristic 2 - 4, every edge on one or two faces.
    welded_of, welded = _welded(data["rest"], faces)
    edges, counts = np.unique(np.sort(welded[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0,
                              return_counts=True)
    assert counts.max() == 2
    assert welded_of.max() + 1 - len(edges) + len(welded) == -2
    loops = _boundary_loops(welded)
    assert len(loops) == 4
    points = [rest[np.flatnonzero(np.isin(welded_of, loop))] for loop in loops]
    centres = np.array([p.mean(axis=0) for p in points])
    order = np.argsort(centres[:, 1])
    waist, collar = points[order[0]], points[order[-1]]
    assert np.allclose(waist[:, 1], lo[1]) and 0.9 * 2 * np.pi * 0.12 < np.ptp(waist[:, 0]) * 2  # around the torso
    assert collar[:, 1].min() > 0.2 and np.ptp(collar[:, 0]) < 0.2  # around the neck
    sleeves = sorted((order[1], order[2]), key=lambda i: centres[i, 0])
    assert centres[sleeves[0], 0] < -0.3 and centres[sleeves[1], 0] > 0.3  # at the ends of the arms


def test_seam_copies_share_positions_in_every_pose(data):
    groups = _seam_groups(data["rest"])
    assert all(len(g) == 2 for g in groups) and len(groups) > 100
    pairs = np.array(groups)
    front = data["uv"][:, 1] >= 0.5
    assert np.all(front[pairs[:, 0]] != front[pairs[:, 1]])  # one copy per piece
    for key in ("gt", "inferred"):
        positions = data[key]
        assert np.array_equal(positions[:, pairs[:, 0]], positions[:, pairs[:, 1]]), key


def test_faces_point_away_from_the_body(data):
    from scipy.spatial import cKDTree

    rest, faces = data["rest"].astype(np.float64), data["faces"]
    body_rest = make_body()[1].astype(np.float64)
    centroid = rest[faces].mean(axis=1)
    _, nearest = cKDTree(body_rest).query(centroid)
    outward = np.einsum("ij,ij->i", _face_normals(rest, faces), centroid - body_rest[nearest])
    assert np.mean(outward > 0) > 0.995
    # In a posed garment, folds aside, faces still face the way the smooth fit does.
    agree = np.einsum("kij,kij->ki", _face_normals(data["gt"], faces), _face_normals(data["inferred"], faces)) > 0
    assert agree.mean() > 0.99


def test_uv_charts(data):
    uv, rest, faces = data["uv"].astype(np.float64), data["rest"].astype(np.float64), data["faces"]
    assert uv.min() >= 0.0 and uv.max() <= 1.0
    chart = uv[faces, 1] >= 0.5
    assert np.all(chart.all(axis=1) | (~chart).all(axis=1))  # no face straddles the two pieces
    d1, d2 = uv[faces[:, 1]] - uv[faces[:, 0]], uv[faces[:, 2]] - uv[faces[:, 0]]
    area = 0.5 * (d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])
    assert np.all(area > 0)  # counter-clockwise in uv, as in 3-D seen from outside: not mirrored
    # No overlap: each piece is bounded by one loop, and its counter-clockwise triangles
    # cover exactly the area that loop encloses.
    for piece in (True, False):
        mine = faces[chart[:, 0] == piece]
        loops = _boundary_loops(mine)
        assert len(loops) == 1
        x, y = uv[loops[0], 0], uv[loops[0], 1]
        enclosed = 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)
        assert area[chart[:, 0] == piece].sum() == pytest.approx(enclosed, rel=1e-9)
    # The front piece faces +z, the back -z; uv grows with +x on the front, -x on the back.
    front_v, back_v = np.unique(faces[chart[:, 0]]), np.unique(faces[~chart[:, 0]])
    assert rest[front_v, 2].mean() > 0.05 and rest[back_v, 2].mean() < -0.05
    assert np.corrcoef(uv[front_v, 0], rest[front_v, 0])[0, 1] > 0.95
    assert np.corrcoef(uv[back_v, 0], rest[back_v, 0])[0, 1] < -0.95
    # uv is the material scaled by one factor: exactly on the torso and sleeves, nearly
    # everywhere else (the yoke, where the pattern wraps the shoulders).
    edges = _edges(faces)
    ratio = np.linalg.norm(uv[edges[:, 1]] - uv[edges[:, 0]], axis=1) / np.linalg.norm(
        rest[edges[:, 1]] - rest[edges[:, 0]], axis=1)
    scale = np.median(ratio)
    assert np.mean(np.abs(ratio / scale - 1) < 0.005) > 0.6
    assert np.quantile(np.abs(ratio / scale - 1), 0.95) < 0.15


def test_gt_keeps_edge_lengths_close_to_rest(data):
    rest, gt, faces = data["rest"].astype(np.float64), data["gt"].astype(np.float64), data["faces"]
    edges = _edges(faces)
    rest_len = np.linalg.norm(rest[edges[:, 1]] - rest[edges[:, 0]], axis=1)
    strain = np.linalg.norm(gt[:, edges[:, 1]] - gt[:, edges[:, 0]], axis=-1) / rest_len - 1.0
    mean_abs = np.abs(strain).mean()
    assert 0.005 < mean_abs < 0.05  # the garment does deform, mostly by folding not stretching
    assert np.abs(strain).max() < 0.5  # no tears or collapsed edges
    assert np.mean(np.abs(strain) > 0.1) < 0.03  # the few: where the spine bends most, and under the arms
    assert mean_abs == pytest.approx(data["stats"]["mean_abs_edge_strain_gt"], rel=1e-3)


def test_fold_statistics(data):
    stats = data["stats"]
    assert 0.01 <= stats["fold_depth_m"] <= 0.03
    assert 0.04 <= stats["fold_wavelength_m"] <= 0.10
    assert stats["max_fold_angle_deg"] > 90  # some folds overhang
    # Independently: gt differs from the smooth fit by folds of centimeter scale...
    gt, inferred = data["gt"].astype(np.float64), data["inferred"].astype(np.float64)
    peak = np.linalg.norm(gt - inferred, axis=-1).max(axis=1)
    assert np.median(peak) > 0.01
    # ...and overhanging folds turn some faces against the smooth surface in some pose.
    agree = np.einsum("kij,kij->ki", _face_normals(gt, data["faces"]), _face_normals(inferred, data["faces"]))
    assert (agree < 0).any()


def test_sleeves_fold_when_the_arms_move():
    faces, uv, rest = make_garment()
    sleeve = np.abs(rest[:, 0]) > 0.3
    still = np.zeros(POSE_DIM)
    still[3:5] = -1.0  # no shrug
    lifted = still.copy()
    lifted[5:7] = 1.0
    from mvtex.synth.shirt import pose_warp

    smooth = pose_warp(lifted)(rest.astype(np.float64))  # the warp alone: no folds
    folded = deform(rest, uv, lifted).astype(np.float64)
    assert np.linalg.norm(folded - smooth, axis=1)[sleeve].max() > 0.008
    unfolded = deform(rest, uv, still).astype(np.float64) - pose_warp(still)(rest.astype(np.float64))
    assert np.abs(unfolded[sleeve]).max() < 1e-6  # arms at rest: no sleeve fold


def _bending(rest: np.ndarray, faces: np.ndarray):
    """The mean squared angle (degrees^2) between the normals of faces that share an edge
    of the sewn mesh (folds bend sharply, a smooth surface gently), a function of
    (K, n, 3) positions."""
    welded = _welded(rest, faces)[1]
    edges = np.sort(np.stack([welded[:, [0, 1]], welded[:, [1, 2]], welded[:, [2, 0]]], axis=1).reshape(-1, 2), axis=1)
    face = np.repeat(np.arange(len(faces)), 3)
    key = edges[:, 0] * (welded.max() + 1) + edges[:, 1]
    order = np.argsort(key, kind="stable")
    shared = key[order][1:] == key[order][:-1]
    left, right = face[order[:-1][shared]], face[order[1:][shared]]

    def bending(positions):
        normals = _face_normals(np.asarray(positions), faces)
        normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
        cos = np.clip(np.einsum("...ij,...ij->...i", normals[..., left, :], normals[..., right, :]), -1.0, 1.0)
        return float(np.mean(np.degrees(np.arccos(cos)) ** 2))

    return bending


def test_inferred_is_smooth_and_off_by_centimeters(data):
    gt, inferred, split = data["gt"], data["inferred"], data["split"]
    test = split["test"]
    rmse = np.sqrt(np.mean(np.sum((inferred[test].astype(np.float64) - gt[test]) ** 2, axis=-1)))
    assert 0.002 < rmse < 0.03
    assert rmse == pytest.approx(data["stats"]["rmse_inferred_test_m"], rel=1e-4)
    # Smooth: of the bending beyond the rest shape's, the fit keeps less than 60 %.
    bending = _bending(data["rest"], data["faces"])
    at_rest = bending(data["rest"][None])
    assert bending(inferred) - at_rest < 0.6 * (bending(gt) - at_rest)


def test_inferred_is_fitted_on_train_poses_only(data):
    # Refitting on the training poses alone reproduces every inferred mesh, test poses included.
    train = data["split"]["train"]
    predictor = fit_predictor(data["gt"][train], data["poses"][train], n_components=6, ridge=1e-2)
    np.testing.assert_array_equal(predictor.predict(data["poses"]), data["inferred"])
    # A linear model in the pose, not a lookup: it fits its training poses only approximately.
    assert data["stats"]["rmse_inferred_train_m"] > 0.002


def test_public_functions_agree_with_synthesize(data):
    faces, uv, rest = make_garment()
    np.testing.assert_array_equal(faces, data["faces"])
    np.testing.assert_array_equal(uv, data["uv"])
    np.testing.assert_array_equal(rest, data["rest"])
    np.testing.assert_array_equal(sample_poses(NUM_POSES, 0), data["poses"])
    body_faces, _ = make_body()
    np.testing.assert_array_equal(body_faces, data["body_faces"])
    for k in (0, 7):
        np.testing.assert_array_equal(deform(rest, uv, data["poses"][k]), data["gt"][k])
        np.testing.assert_array_equal(pose_body(data["poses"][k]), data["body"][k])


def _clearance_poses(pose_dim: int) -> np.ndarray:
    """Random poses and the extremes: every component at -1 and +1, all at once."""
    poses = [np.full(pose_dim, s) for s in (-1.0, 1.0)]
    for i in range(min(pose_dim, 7)):
        for s in (-1.0, 1.0):
            p = np.zeros(pose_dim)
            p[i] = s
            poses.append(p)
    return np.array(poses + list(np.random.default_rng(5).uniform(-1, 1, (4, pose_dim))), dtype=np.float32)


@pytest.mark.slow
@pytest.mark.parametrize("garment", ["shirt", "skirt"])
def test_gt_never_cuts_into_the_body(garment):
    """An exact point-to-triangle search (and a ray-cast inside test) against the body
    mesh: the gt cloth keeps a few millimeters clear of the body in every pose; the
    inferred meshes of the same poses are only checked to be measurable."""
    import trimesh

    from mvtex.synth import shirt, skirt

    module = shirt if garment == "shirt" else skirt
    faces, uv, rest = module.make_garment()
    body_faces, _ = module.make_body()
    least = np.inf
    for pose in _clearance_poses(module.POSE_DIM):
        cloth = (module.deform(rest, uv, pose) if garment == "shirt" else module.deform(pose)).astype(np.float64)
        body = module.pose_body(pose).astype(np.float64)
        distance = mesh_distance(cloth, body, body_faces, cutoff=0.035)  # exact below 1 cm at least
        least = min(least, distance.min())
        assert not trimesh.Trimesh(body, body_faces, process=False).contains(cloth).any()
    assert least > 0.003


@pytest.mark.slow
def test_clearance_statistics_match_an_exact_search():
    import trimesh

    small = synthesize(SynthOptions(num_poses=6, seed=4))
    exact, inside = [], []
    for k in range(6):
        body = small["body"][k].astype(np.float64)
        exact.append(mesh_distance(small["gt"][k], body, small["body_faces"]).min())
        inside.append(trimesh.Trimesh(body, small["body_faces"], process=False).contains(
            np.unique(small["inferred"][k].astype(np.float64), axis=0)).mean())
    assert small["stats"]["clearance_m"] == pytest.approx(min(exact), abs=1e-6)
    assert small["stats"]["inferred_inside_body_fraction"] == pytest.approx(np.mean(inside), abs=2e-3)


def test_the_arm_lift_turns_the_arm_by_its_angle():
    from mvtex.synth.shirt import ARM_LIFT
    from mvtex.synth.shirt_shape import SHOULDER_JOINT

    body_faces, body_rest = make_body()
    body_rest = body_rest.astype(np.float64)
    faces, uv, rest = make_garment()
    pose = np.zeros(POSE_DIM)
    pose[3:5] = -1.0  # no shrug; no bend, no twist
    pose[5], pose[6] = 0.5, -0.75
    posed = pose_body(pose).astype(np.float64)
    cloth = deform(rest, uv, pose).astype(np.float64)
    for side, lift in ((-1.0, 0.5), (1.0, -0.75)):
        joint = SHOULDER_JOINT * np.array([side, 1.0, 1.0])
        tip = body_rest[:, 0] * side > 0.36  # the end of the upper arm
        before, after = body_rest[tip] - joint, posed[tip] - joint
        turned = np.arctan2(after[:, 1], after[:, 0] * side) - np.arctan2(before[:, 1], before[:, 0] * side)
        np.testing.assert_allclose(turned, lift * ARM_LIFT, atol=2e-6)  # float32 positions
        np.testing.assert_allclose(np.linalg.norm(after, axis=1), np.linalg.norm(before, axis=1), atol=1e-6)
        np.testing.assert_allclose(after[:, 2], before[:, 2], atol=1e-6)
        # The sleeve end goes along (folds aside): its centre turns by the same angle.
        end = rest[:, 0] * side > np.abs(rest[:, 0]).max() - 1e-4
        c0, c1 = rest[end].mean(axis=0) - joint, cloth[end].mean(axis=0) - joint
        angle = np.arctan2(c1[1], c1[0] * side) - np.arctan2(c0[1], c0[0] * side)
        assert np.degrees(abs(angle - lift * ARM_LIFT)) < 2.0
    # Nothing else moves without a bend: the neck stays where it was.
    neck = body_rest[:, 1] > 0.35
    np.testing.assert_allclose(posed[neck], body_rest[neck], atol=1e-7)


def test_bending_forward_carries_neck_and_collar_forward():
    faces, uv, rest = make_garment()
    body_rest = make_body()[1].astype(np.float64)
    pose = np.zeros(POSE_DIM)
    pose[0] = 1.0
    body, cloth = pose_body(pose).astype(np.float64), deform(rest, uv, pose).astype(np.float64)
    neck = body_rest[:, 1] > 0.35
    collar = rest[:, 1] > 0.25
    neck_forward, collar_forward = (body[neck, 2] - body_rest[neck, 2]), (cloth[collar, 2] - rest[collar, 2])
    assert neck_forward.min() > 0.02 and collar_forward.min() > 0.005
    assert neck_forward.mean() > collar_forward.mean() > 0.01  # the higher, the farther


def test_body_mesh_is_closed_and_outward():
    for module in ("shirt", "skirt"):
        from importlib import import_module

        faces, vertices = import_module(f"mvtex.synth.{module}").make_body()
        edges, counts = np.unique(np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0,
                                  return_counts=True)
        assert np.all(counts == 2), module  # closed, manifold
        v = vertices.astype(np.float64)
        volume = np.einsum("ij,ij->i", v[faces[:, 0]], np.cross(v[faces[:, 1]], v[faces[:, 2]])).sum() / 6
        assert volume > 0.01, module  # counter-clockwise seen from outside encloses a positive volume
        assert len(v) - len(edges) + len(faces) == 2, module  # one sphere


def test_deterministic_for_a_seed():
    first = synthesize(SynthOptions(num_poses=5, seed=3))
    second = synthesize(SynthOptions(num_poses=5, seed=3))
    other = synthesize(SynthOptions(num_poses=5, seed=4))
    for key in ("faces", "uv", "rest", "gt", "inferred", "poses", "body", "body_faces"):
        np.testing.assert_array_equal(first[key], second[key])
    assert first["split"] == second["split"] and first["stats"] == second["stats"]
    assert not np.array_equal(first["gt"], other["gt"])
    assert not np.array_equal(first["poses"], other["poses"])


@pytest.mark.parametrize("count", [2, MAX_POSES + 1, 10**12, 3.5, True])
def test_pose_counts_are_bounded_before_anything_is_allocated(count):
    with pytest.raises(ValueError, match="num_poses"):
        synthesize(SynthOptions(num_poses=count))
    with pytest.raises(ValueError, match="num_poses"):
        write_synth("/nonexistent/never/written", SynthOptions(num_poses=count))


def test_without_body_the_garment_is_alone(tmp_path):
    from mvtex.data.dataset import load_dataset

    plain = synthesize(SynthOptions(num_poses=5, seed=1, body=False))
    bodied = synthesize(SynthOptions(num_poses=5, seed=1))
    assert plain["body"] is None and plain["body_faces"] is None
    assert not any(k.startswith(("clearance", "body", "inferred_inside")) for k in plain["stats"])
    for key in ("gt", "inferred", "poses"):  # the cloth is the same either way
        np.testing.assert_array_equal(plain[key], bodied[key])
    write_synth(tmp_path / "plain", SynthOptions(num_poses=5, seed=1, body=False))
    assert not (tmp_path / "plain" / "body.npy").exists() and not (tmp_path / "plain" / "body.npz").exists()
    assert load_dataset(tmp_path / "plain").body is None


@pytest.mark.slow
def test_write_synth_saves_what_synthesize_returns(tmp_path):
    import json

    from mvtex.data.dataset import load_dataset

    options = SynthOptions(num_poses=6, seed=1)
    result = write_synth(tmp_path / "shirt", options)
    data = synthesize(options)
    assert result.stats == data["stats"] and result.to_json() == data["stats"] and result.options == options
    stored = json.loads((tmp_path / "shirt" / "dataset.json").read_text())["stats"]
    assert stored == json.loads(json.dumps(result.stats))
    meta = json.loads((tmp_path / "shirt" / "dataset.json").read_text())
    assert (meta["num_poses"], meta["num_vertices"], meta["pose_dim"]) == (6, len(data["rest"]), POSE_DIM)
    assert meta["body"] == {"num_vertices": data["body"].shape[1], "num_faces": len(data["body_faces"])}
    ds = load_dataset(tmp_path / "shirt")
    np.testing.assert_array_equal(ds.gt, data["gt"])
    np.testing.assert_array_equal(ds.inferred, data["inferred"])
    np.testing.assert_array_equal(ds.body.positions, data["body"])
    np.testing.assert_array_equal(ds.body.faces, data["body_faces"])
    assert ds.split == data["split"]


# -- the second garment: a flared skirt with hem flutes, on hips and legs ------------------------


@pytest.mark.slow
def test_skirt_mesh_uv_and_frame(skirt):
    faces, uv, rest = skirt["faces"], skirt["uv"].astype(np.float64), skirt["rest"].astype(np.float64)
    n = len(rest)
    assert skirt["name"] == "skirt" and 2000 <= n <= 4000
    assert faces.dtype == np.int32 and faces.min() == 0 and faces.max() == n - 1
    assert skirt["gt"].shape == skirt["inferred"].shape == (NUM_POSES, n, 3)
    assert skirt["body"].shape[:1] == (NUM_POSES,) and len(skirt["body_faces"]) <= 5000
    lo, hi = rest.min(axis=0), rest.max(axis=0)
    assert np.all(np.abs((lo + hi) / 2) < 0.03)
    # A cone: waist radius 0.15 m on top, hem radius 0.30 m at the bottom, about 0.54 m tall.
    radius = np.hypot(rest[:, 0], rest[:, 2])
    top, bottom = rest[:, 1] > hi[1] - 1e-6, rest[:, 1] < lo[1] + 1e-6
    assert np.allclose(radius[top], 0.15, atol=1e-5) and np.allclose(radius[bottom], 0.30, atol=1e-5)
    assert 0.5 <= hi[1] - lo[1] <= 0.6
    # Faces point away from the axis; no face straddles the two charts (v < 0.5, v > 0.5).
    normals = _face_normals(rest, faces)
    radial = rest[faces].mean(axis=1) * np.array([1.0, 0.0, 1.0])
    assert np.all(np.einsum("ij,ij->i", normals, radial) > 0)
    chart = uv[faces, 1] >= 0.5
    assert np.all(chart.all(axis=1) | (~chart).all(axis=1))
    assert uv.min() >= 0.0 and uv.max() <= 1.0
    d1, d2 = uv[faces[:, 1]] - uv[faces[:, 0]], uv[faces[:, 2]] - uv[faces[:, 0]]
    assert np.all(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0] > 0)  # not mirrored
    # A cone unrolls without distortion: every edge has one uv-per-meter ratio.
    edges = _edges(faces)
    ratio = np.linalg.norm(uv[edges[:, 1]] - uv[edges[:, 0]], axis=1) / np.linalg.norm(
        rest[edges[:, 1]] - rest[edges[:, 0]], axis=1)
    assert np.ptp(ratio) / np.median(ratio) < 0.01
    # Sewn, it is a tube: two boundary loops (waist and hem).
    assert len(_boundary_loops(_welded(skirt["rest"], faces)[1])) == 2


@pytest.mark.slow
def test_skirt_seam_copies_share_positions(skirt):
    pairs = np.array(_seam_groups(skirt["rest"]))
    assert pairs.shape[1] == 2 and len(pairs) == 2 * len(np.unique(skirt["rest"][:, 1]))
    for key in ("gt", "inferred"):
        assert np.array_equal(skirt[key][:, pairs[:, 0]], skirt[key][:, pairs[:, 1]]), key


def test_skirt_keeps_lengths_and_folds_by_centimeters_with_overhangs(skirt):
    rest, gt, inferred, faces = (skirt[k].astype(np.float64) if k != "faces" else skirt[k]
                                 for k in ("rest", "gt", "inferred", "faces"))
    edges = _edges(faces)
    rest_len = np.linalg.norm(rest[edges[:, 1]] - rest[edges[:, 0]], axis=1)
    strain = np.linalg.norm(gt[:, edges[:, 1]] - gt[:, edges[:, 0]], axis=-1) / rest_len - 1.0
    assert 0.005 < np.abs(strain).mean() < 0.05 and np.abs(strain).max() < 0.5
    # Around each ring the flutes keep the ring's material length: compare the polyline
    # length of each gt ring with the rest ring's.
    for y in np.unique(rest[:, 1])[[0, 5, -1]]:
        ring = np.flatnonzero((np.abs(rest[:, 1] - y) < 1e-7) & (skirt["uv"][:, 1] >= 0.5))  # front chart
        order = ring[np.argsort(skirt["uv"][ring, 0])]
        rest_length = np.linalg.norm(np.diff(rest[order], axis=0), axis=1).sum()
        gt_length = np.linalg.norm(np.diff(gt[:, order], axis=1), axis=2).sum(axis=1)
        assert np.abs(gt_length / rest_length - 1.0).max() < 0.03
    stats = skirt["stats"]
    assert 0.01 <= stats["fold_depth_m"] <= 0.035 and 0.04 <= stats["fold_wavelength_m"] <= 0.12
    assert stats["max_fold_angle_deg"] > 90 and 0.0 < stats["overhanging_pose_fraction"] < 1.0
    # Independently: flutes put gt centimeters off the smooth fit near the hem, and
    # overhanging ones turn faces against it.
    assert np.median(np.linalg.norm(gt - inferred, axis=-1).max(axis=1)) > 0.01
    agree = np.einsum("kij,kij->ki", _face_normals(gt, faces), _face_normals(inferred, faces))
    assert (agree < 0).any() and (agree > 0).mean() > 0.97


def test_skirt_inferred_is_fitted_not_blurred(skirt):
    train, test = skirt["split"]["train"], skirt["split"]["test"]
    predictor = fit_predictor(skirt["gt"][train], skirt["poses"][train], n_components=6, ridge=1e-2)
    np.testing.assert_array_equal(predictor.predict(skirt["poses"]), skirt["inferred"])
    rmse = np.sqrt(np.mean(np.sum((skirt["inferred"][test].astype(np.float64) - skirt["gt"][test]) ** 2, axis=-1)))
    assert 0.002 < rmse < 0.03 and skirt["stats"]["rmse_inferred_train_m"] > 0.002
    bending = _bending(skirt["rest"], skirt["faces"])
    at_rest = bending(skirt["rest"][None])
    assert bending(skirt["inferred"]) - at_rest < 0.6 * (bending(skirt["gt"]) - at_rest)


def test_the_legs_swing_with_the_hem():
    from mvtex.synth import skirt as skirt_module

    _, body_rest = skirt_module.make_body()
    faces, uv, rest = skirt_module.make_garment()
    knee = body_rest[:, 1] < -0.38
    hem = rest[:, 1] < rest[:, 1].min() + 1e-6
    for pose_index, axis in ((0, 2), (1, 0)):  # forward / back swing moves z, sideways moves x
        pose = np.zeros(skirt_module.POSE_DIM)
        pose[pose_index] = 1.0
        legs = skirt_module.pose_body(pose)[knee].mean(axis=0) - body_rest[knee].mean(axis=0)
        cloth = skirt_module.deform(pose)[hem].mean(axis=0) - rest[hem].mean(axis=0)
        assert legs[axis] > 0.03 and cloth[axis] > 0.03


def test_builtin_rigs_frame_both_dressed_mannequins(data, skirt):
    """Every vertex of every pose, cloth and body, projects inside every camera of the shipped
    rigs (tested on their convex hull: in front of a camera, what is inside the hull
    projects inside the hull's image)."""
    from scipy.spatial import ConvexHull

    from mvtex.data.rig import load_rig, resolve_rig

    points = []
    for d in (data, skirt):
        for key in ("gt", "inferred", "body"):
            p = d[key].reshape(-1, 3).astype(np.float64)
            points.append(p[ConvexHull(p).vertices])
    for rig_name in ("stereo", "square4", "trapezoid12"):
        for cam in load_rig(resolve_rig(rig_name)):
            for p in points:
                assert np.all(p @ cam.R[2] + cam.t.ravel()[2] > 0.5)  # well in front
                pixels = cam.project(p)[0]
                assert pixels.min() > 10
                assert pixels[:, 0].max() < cam.width - 10 and pixels[:, 1].max() < cam.height - 10


@pytest.mark.slow
@pytest.mark.gl
def test_the_body_hides_the_inside_of_the_shirt(gl):
    """Through the collar, the waist and the sleeve ends the cameras of the shipped rigs
    would see the shirt's inside; with the mannequin in front, only slivers at the rims remain."""
    from mvtex.data.rig import load_rig, resolve_rig
    from mvtex.render.raster import rasterize

    faces, uv, rest = make_garment()
    body_faces, _ = make_body()
    cameras = [c for rig in ("stereo", "square4", "trapezoid12") for c in load_rig(resolve_rig(rig))]
    seen = {False: [0, 0], True: [0, 0]}
    for pose in sample_poses(3, 11):
        cloth, body = deform(rest, uv, pose).astype(np.float64), pose_body(pose).astype(np.float64)
        normals = _face_normals(cloth, faces)
        for cam in cameras:
            centre = -cam.R.T @ cam.t.ravel()
            for with_body in (False, True):
                positions = np.concatenate([cloth, body]) if with_body else cloth
                all_faces = np.concatenate([faces, body_faces + len(cloth)]) if with_body else faces
                tri = rasterize(gl, positions, all_faces, cam, attributes=False).tri_id
                shown = tri[(tri >= 0) & (tri < len(faces))]
                inside = np.einsum("ij,ij->i", cloth[faces[shown]].mean(axis=1) - centre, normals[shown]) > 0
                seen[with_body][0] += int(inside.sum())
                seen[with_body][1] += len(shown)
    without, with_body = seen[False][0] / seen[False][1], seen[True][0] / seen[True][1]
    assert without > 0.02  # the openings do show the inside of a bare shirt...
    assert with_body < 0.01 and with_body < 0.2 * without  # ...and the body covers nearly all of it


def test_unknown_garment_is_refused():
    with pytest.raises(ValueError, match="garment"):
        synthesize(SynthOptions(num_poses=5, garment="scarf"))


def test_cli_synth_records_the_garment(tmp_path):
    import json

    from mvtex.cli import main

    assert main(["synth", "--out", str(tmp_path / "s"), "--num-poses", "10", "--garment", "skirt", "--json"]) == 0
    meta = json.loads((tmp_path / "s" / "dataset.json").read_text())
    assert meta["garment"] == "skirt" and meta["name"] == "skirt"
    assert main(["synth", str(tmp_path / "t"), "--poses", "10", "--garment", "scarf"]) == 2


def test_skirt_public_functions_agree_with_synthesize(skirt):
    from mvtex.synth import skirt as skirt_module

    faces, uv, rest = skirt_module.make_garment()
    for mine, theirs in ((faces, "faces"), (uv, "uv"), (rest, "rest")):
        np.testing.assert_array_equal(mine, skirt[theirs])
    np.testing.assert_array_equal(skirt_module.sample_poses(NUM_POSES, 0), skirt["poses"])
    np.testing.assert_array_equal(skirt_module.make_body()[0], skirt["body_faces"])
    for k in (0, 7):
        np.testing.assert_array_equal(skirt_module.deform(skirt["poses"][k]), skirt["gt"][k])
        np.testing.assert_array_equal(skirt_module.pose_body(skirt["poses"][k]), skirt["body"][k])


@pytest.mark.slow
@pytest.mark.parametrize("garment,body", [("shirt", True), ("skirt", True), ("shirt", False)])
def test_streamed_write_equals_save_dataset_byte_for_byte(tmp_path, monkeypatch, garment, body):
    """write_synth streams blocks of poses to disk; with blocks of 4 poses its files must be
    exactly those `dataset.save_dataset` writes for the in-memory `synthesize` result."""
    import mvtex.synth.generate as synth
    from mvtex.data.dataset import save_dataset

    options = SynthOptions(num_poses=10, seed=2, garment=garment, body=body)
    save_dataset(tmp_path / "memory", garment=garment, **synthesize(options))
    monkeypatch.setattr(synth, "_CHUNK", 4)
    write_synth(tmp_path / "streamed", options)
    # Every file but the manifests, which name the writer ("save_dataset", "synth").
    names = sorted(p.name for p in (tmp_path / "memory").iterdir() if p.name != ".mvtex-output.json")
    assert names == sorted(p.name for p in (tmp_path / "streamed").iterdir() if p.name != ".mvtex-output.json")
    assert ("body.npy" in names) == body
    for name in names:
        assert (tmp_path / "memory" / name).read_bytes() == (tmp_path / "streamed" / name).read_bytes(), name
