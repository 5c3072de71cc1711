"""Properties of the built-in garment dataset (mvtex.synth.generate), measured independently.

Every quantity is recomputed here from the arrays (edges from faces, seams from equal
rest positions, normals from cross products), not read back from `stats` alone.
"""

from __future__ import annotations

import numpy as np
import pytest

from mvtex.synth.generate import SynthOptions, synthesize, write_synth
from mvtex.synth.predictor import fit_predictor
from mvtex.synth.shirt import POSE_DIM, deform, make_garment, sample_poses

NUM_POSES = 60


@pytest.fixture(scope="module")
def data() -> dict:
    return synthesize(SynthOptions(num_poses=NUM_POSES, seed=0))


def _edges(faces: np.ndarray) -> np.ndarray:
    """Unique undirected edges (e, 2) of a triangle list."""
    pairs = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    return np.unique(np.sort(pairs, axis=1), axis=0)


def _seam_pairs(rest: np.ndarray) -> np.ndarray:
    """(s, 2) indices of vertices that share a rest position (the split seam copies)."""
    order = np.lexsort(rest.T)
    same = np.all(rest[order[1:]] == rest[order[:-1]], axis=1)
    return np.stack([order[:-1][same], order[1:][same]], axis=1)


def _face_normals(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    p = positions.astype(np.float64)
    return np.cross(p[..., faces[:, 1], :] - p[..., faces[:, 0], :], p[..., faces[:, 2], :] - p[..., faces[:, 0], :])


def test_shapes_dtypes_and_split(data):
    faces, uv, rest = data["faces"], data["uv"], data["rest"]
    n = len(rest)
    assert 2500 <= n <= 3500
    assert data["name"] == "shirt"
    assert faces.dtype == np.int32 and faces.ndim == 2 and faces.shape[1] == 3
    assert faces.min() == 0 and faces.max() == n - 1
    assert uv.dtype == np.float32 and uv.shape == (n, 2)
    assert rest.dtype == np.float32 and rest.shape == (n, 3)
    for key in ("gt", "inferred"):
        assert data[key].dtype == np.float32 and data[key].shape == (NUM_POSES, n, 3)
        assert np.isfinite(data[key]).all()
    poses = data["poses"]
    assert poses.dtype == np.float32 and poses.shape == (NUM_POSES, POSE_DIM)
    assert 8 <= POSE_DIM <= 16
    assert poses.min() >= -1.0 and poses.max() <= 1.0
    split = data["split"]
    assert sorted(split["train"] + split["val"] + split["test"]) == list(range(NUM_POSES))
    assert (len(split["train"]), len(split["val"]), len(split["test"])) == (48, 6, 6)
    assert data["stats"]["num_vertices"] == n and data["stats"]["num_faces"] == len(faces)
    assert all(isinstance(v, float) for v in data["stats"].values())


def test_rest_garment_size_and_frame(data):
    rest = data["rest"].astype(np.float64)
    lo, hi = rest.min(axis=0), rest.max(axis=0)
    assert np.all(np.abs((lo + hi) / 2) < 0.03)  # centred near the origin
    width, height, depth = hi - lo
    assert 0.6 <= height <= 0.7  # y is up
    assert 0.32 <= width <= 0.40 and 0.18 <= depth <= 0.26
    # Open at collar and waist: every boundary edge lies on the top or bottom ring, or
    # on a side seam (a UV chart border, closed in 3-D by its copy).
    faces = data["faces"]
    pairs = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    edges, count = np.unique(pairs, axis=0, return_counts=True)
    boundary = edges[count == 1]
    on_ring = np.all(np.abs(np.abs(rest[boundary, 1]) - height / 2) < 1e-6, axis=1)
    on_seam = np.all(np.abs(rest[boundary, 2]) < 1e-6, axis=1)  # seams at the widest x, z = 0
    assert np.all(on_ring | on_seam) and on_ring.any() and on_seam.any()


def test_seam_copies_share_positions_in_every_pose(data):
    pairs = _seam_pairs(data["rest"])
    # One pair per ring on each of the two side seams.
    rings = len(np.unique(data["rest"][:, 1]))
    assert len(pairs) == 2 * rings
    uv = data["uv"]
    assert np.all((uv[pairs[:, 0], 0] < 0.5) != (uv[pairs[:, 1], 0] < 0.5))  # one copy per chart
    for key in ("gt", "inferred"):
        positions = data[key]
        assert np.array_equal(positions[:, pairs[:, 0]], positions[:, pairs[:, 1]]), key


def test_faces_point_outward(data):
    rest, faces = data["rest"].astype(np.float64), data["faces"]
    normals = _face_normals(rest, faces)
    centroid = rest[faces].mean(axis=1)
    radial = centroid * np.array([1.0, 0.0, 1.0])  # away from the tube axis (the y axis)
    assert np.all(np.einsum("ij,ij->i", normals, radial) > 0)
    # In a posed garment, folds aside, faces still face the way the smooth fit does.
    agree = np.einsum("kij,kij->ki", _face_normals(data["gt"], faces), _face_normals(data["inferred"], faces)) > 0
    assert agree.mean() > 0.99


def test_uv_charts(data):
    uv, rest, faces = data["uv"].astype(np.float64), data["rest"].astype(np.float64), data["faces"]
    assert uv.min() >= 0.0 and uv.max() <= 1.0
    chart = uv[faces, 0] >= 0.5
    assert np.all(chart.all(axis=1) | (~chart).all(axis=1))  # no face straddles the charts
    front, back = faces[~chart[:, 0]], faces[chart[:, 0]]
    assert len(front) == len(back) > 0
    assert uv[front, 0].max() < uv[back, 0].min()  # disjoint
    # Front panel on the +z side; u grows with +x on the front and with -x on the back
    # (left to right as each panel is seen from its own outside).
    front_v, back_v = np.unique(front), np.unique(back)
    assert np.all(rest[front_v, 2] >= -1e-6) and np.all(rest[back_v, 2] <= 1e-6)
    assert np.corrcoef(uv[front_v, 0], rest[front_v, 0])[0, 1] > 0.95
    assert np.corrcoef(uv[back_v, 0], rest[back_v, 0])[0, 1] < -0.95
    # Not mirrored: counter-clockwise in UV, as in 3-D seen from outside.
    d1, d2 = uv[faces[:, 1]] - uv[faces[:, 0]], uv[faces[:, 2]] - uv[faces[:, 0]]
    assert np.all(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0] > 0)
    # Proportional to rest arc length: one scale for all edges, either direction.
    edges = _edges(faces)
    ratio = np.linalg.norm(uv[edges[:, 1]] - uv[edges[:, 0]], axis=1) / np.linalg.norm(
        rest[edges[:, 1]] - rest[edges[:, 0]], axis=1)
    assert np.ptp(ratio) / np.median(ratio) < 0.01


def test_gt_keeps_edge_lengths_close_to_rest(data):
    rest, gt, faces = data["rest"].astype(np.float64), data["gt"].astype(np.float64), data["faces"]
    edges = _edges(faces)
    rest_len = np.linalg.norm(rest[edges[:, 1]] - rest[edges[:, 0]], axis=1)
    strain = np.linalg.norm(gt[:, edges[:, 1]] - gt[:, edges[:, 0]], axis=-1) / rest_len - 1.0
    mean_abs = np.abs(strain).mean()
    assert 0.005 < mean_abs < 0.05  # the garment does deform, mostly by folding not stretching
    assert np.abs(strain).max() < 0.5  # no tears or collapsed edges
    assert mean_abs == pytest.approx(data["stats"]["mean_abs_edge_strain_gt"], rel=1e-3)


def test_fold_statistics(data):
    stats = data["stats"]
    assert 0.01 <= stats["fold_depth_m"] <= 0.03
    assert 0.04 <= stats["fold_wavelength_m"] <= 0.10
    assert stats["max_fold_angle_deg"] > 90  # some folds overhang
    # Independently: gt differs from the smooth fit by folds of centimetre scale...
    gt, inferred = data["gt"].astype(np.float64), data["inferred"].astype(np.float64)
    peak = np.linalg.norm(gt - inferred, axis=-1).max(axis=1)
    assert np.median(peak) > 0.01
    # ...and overhanging folds turn some faces against the smooth surface in some pose.
    agree = np.einsum("kij,kij->ki", _face_normals(gt, data["faces"]), _face_normals(inferred, data["faces"]))
    assert (agree < 0).any()


def _grid_laplacian(rest: np.ndarray, faces: np.ndarray):
    """Umbrella operator over the grid edges (purely around or purely up, in rest) of the
    mesh with seam copies merged. Returns (first, apply, interior): `first` (m,) picks one
    vertex per merged position, `apply` maps (K, m, 3) to (K, m, 3), `interior` (m,) masks
    out the collar and waist rings."""
    _, first, merged = np.unique(rest, axis=0, return_index=True, return_inverse=True)
    edges = _edges(merged.reshape(-1)[faces])
    r = rest[first].astype(np.float64)
    d = r[edges[:, 1]] - r[edges[:, 0]]
    edges = edges[(np.abs(d[:, 1]) < 1e-6) | (np.hypot(d[:, 0], d[:, 2]) < 1e-6)]
    degree = np.bincount(edges.ravel(), minlength=len(first))[None, :, None]

    def apply(x: np.ndarray) -> np.ndarray:
        total = np.zeros_like(x)
        np.add.at(total, (slice(None), edges[:, 0]), x[:, edges[:, 1]])
        np.add.at(total, (slice(None), edges[:, 1]), x[:, edges[:, 0]])
        return total / degree - x

    interior = np.abs(r[:, 1]) < r[:, 1].max() - 0.03
    return first, apply, interior


def test_inferred_is_smooth_and_off_by_centimetres(data):
    gt, inferred, split = data["gt"], data["inferred"], data["split"]
    test = split["test"]
    rmse = np.sqrt(np.mean(np.sum((inferred[test].astype(np.float64) - gt[test]) ** 2, axis=-1)))
    assert 0.002 < rmse < 0.03
    assert rmse == pytest.approx(data["stats"]["rmse_inferred_test_m"], rel=1e-4)

    # Roughness: the grid Laplacian applied twice is ~0 on the smooth rest tube and large
    # on folds. The predictor's meshes must be clearly smoother than the ground truth.
    first, laplacian, interior = _grid_laplacian(data["rest"], data["faces"])

    def roughness(positions: np.ndarray) -> float:
        x = positions[:, first].astype(np.float64)
        return float(np.linalg.norm(laplacian(laplacian(x)), axis=-1)[:, interior].mean())

    assert roughness(inferred) < 0.75 * roughness(gt)
    assert roughness(data["rest"][None]) < 0.1 * roughness(gt)


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
    for k in (0, 7):
        np.testing.assert_array_equal(deform(rest, uv, data["poses"][k]), data["gt"][k])


def test_deterministic_for_a_seed():
    first = synthesize(SynthOptions(num_poses=12, seed=3))
    second = synthesize(SynthOptions(num_poses=12, seed=3))
    other = synthesize(SynthOptions(num_poses=12, seed=4))
    for key in ("faces", "uv", "rest", "gt", "inferred", "poses"):
        np.testing.assert_array_equal(first[key], second[key])
    assert first["split"] == second["split"] and first["stats"] == second["stats"]
    assert not np.array_equal(first["gt"], other["gt"])
    assert not np.array_equal(first["poses"], other["poses"])


def test_garment_stays_in_its_box(data):
    box = np.array([0.38, 0.42, 0.3])
    for key in ("gt", "inferred"):
        assert np.all(np.abs(data[key]).max(axis=(0, 1)) < box), key


def test_too_few_poses_is_refused():
    with pytest.raises(ValueError, match="num_poses"):
        synthesize(SynthOptions(num_poses=2))


def test_write_synth_saves_what_synthesize_returns(tmp_path):
    import json

    options = SynthOptions(num_poses=10, seed=1)
    stats = write_synth(tmp_path / "shirt", options)
    data = synthesize(options)
    assert stats == data["stats"]
    meta = json.loads((tmp_path / "shirt" / "dataset.json").read_text())
    assert (meta["num_poses"], meta["num_vertices"], meta["pose_dim"]) == (10, len(data["rest"]), POSE_DIM)
    np.testing.assert_array_equal(np.load(tmp_path / "shirt" / "gt.npy"), data["gt"])
    np.testing.assert_array_equal(np.load(tmp_path / "shirt" / "inferred.npy"), data["inferred"])
    split = json.loads((tmp_path / "shirt" / "split.json").read_text())
    assert split == data["split"]


# -- the second garment: a flared skirt with hem flutes ------------------------------------------


@pytest.fixture(scope="module")
def skirt() -> dict:
    return synthesize(SynthOptions(num_poses=NUM_POSES, seed=0, garment="skirt"))


def test_skirt_mesh_uv_and_frame(skirt):
    faces, uv, rest = skirt["faces"], skirt["uv"].astype(np.float64), skirt["rest"].astype(np.float64)
    n = len(rest)
    assert skirt["name"] == "skirt" and 2000 <= n <= 4000
    assert faces.dtype == np.int32 and faces.min() == 0 and faces.max() == n - 1
    assert skirt["gt"].shape == skirt["inferred"].shape == (NUM_POSES, n, 3)
    assert skirt["poses"].shape == (NUM_POSES, POSE_DIM)
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
    # Borders: waist and hem rings, and the two side seams (x = -+r, z = 0).
    pairs = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    e, count = np.unique(pairs, axis=0, return_counts=True)
    boundary = e[count == 1]
    on_ring = np.all(top[boundary], axis=1) | np.all(bottom[boundary], axis=1)
    on_seam = np.all(np.abs(rest[boundary, 2]) < 1e-6, axis=1)
    assert np.all(on_ring | on_seam) and on_seam.any()


def test_skirt_seam_copies_share_positions(skirt):
    pairs = _seam_pairs(skirt["rest"])
    assert len(pairs) == 2 * len(np.unique(skirt["rest"][:, 1]))
    for key in ("gt", "inferred"):
        assert np.array_equal(skirt[key][:, pairs[:, 0]], skirt[key][:, pairs[:, 1]]), key


def test_skirt_keeps_lengths_and_folds_by_centimetres_with_overhangs(skirt):
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
    # Independently: flutes put gt centimetres off the smooth fit near the hem, and
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
    # Smoother than gt around the rings: second differences along each ring.
    rest = skirt["rest"]
    front = skirt["uv"][:, 1] >= 0.5
    rings = [np.flatnonzero((rest[:, 1] == y) & front) for y in np.unique(rest[:, 1])]
    rings = [r[np.argsort(skirt["uv"][r, 0])] for r in rings]

    def roughness(positions):
        return float(np.mean([np.linalg.norm(np.diff(positions[:, r], 2, axis=1), axis=-1).mean() for r in rings]))

    assert roughness(skirt["inferred"].astype(np.float64)) < 0.75 * roughness(skirt["gt"].astype(np.float64))


def test_builtin_rigs_frame_both_garments(shirt_and_skirt_extremes):
    """Every vertex of every pose projects inside every camera of the shipped rigs."""
    from mvtex.data.rig import load_rig, resolve_rig

    for rig_name in ("stereo", "square4", "trapezoid12"):
        for cam in load_rig(resolve_rig(rig_name)):
            for positions in shirt_and_skirt_extremes:
                pixels = cam.project(positions.reshape(-1, 3).astype(np.float64))[0]
                assert pixels.min() > 10
                assert pixels[:, 0].max() < cam.width - 10 and pixels[:, 1].max() < cam.height - 10


@pytest.fixture(scope="module")
def shirt_and_skirt_extremes(data, skirt):
    return [data["gt"], data["inferred"], skirt["gt"], skirt["inferred"]]


def test_unknown_garment_is_refused():
    with pytest.raises(ValueError, match="garment"):
        synthesize(SynthOptions(num_poses=5, garment="scarf"))


def test_cli_synth_records_the_garment(tmp_path):
    import json

    from mvtex.cli import main

    assert main(["synth", str(tmp_path / "s"), "--poses", "10", "--garment", "skirt", "--json"]) == 0
    meta = json.loads((tmp_path / "s" / "dataset.json").read_text())
    assert meta["garment"] == "skirt" and meta["name"] == "skirt"
    assert main(["synth", str(tmp_path / "t"), "--poses", "10", "--garment", "scarf"]) == 2


def test_skirt_public_functions_agree_with_synthesize(skirt):
    from mvtex.synth import skirt as skirt_module

    faces, uv, rest = skirt_module.make_garment()
    for mine, theirs in ((faces, "faces"), (uv, "uv"), (rest, "rest")):
        np.testing.assert_array_equal(mine, skirt[theirs])
    for k in (0, 7):
        np.testing.assert_array_equal(skirt_module.deform(skirt["poses"][k]), skirt["gt"][k])


@pytest.mark.parametrize("garment", ["shirt", "skirt"])
def test_streamed_write_equals_save_dataset_byte_for_byte(tmp_path, monkeypatch, garment):
    """write_synth streams blocks of poses to disk; with blocks of 4 poses its files must be
    exactly those `dataset.save_dataset` writes for the in-memory `synthesize` result."""
    import mvtex.synth.generate as synth
    from mvtex.data.dataset import save_dataset

    options = SynthOptions(num_poses=10, seed=2, garment=garment)
    save_dataset(tmp_path / "memory", garment=garment, **synthesize(options))
    monkeypatch.setattr(synth, "_CHUNK", 4)
    write_synth(tmp_path / "streamed", options)
    names = sorted(p.name for p in (tmp_path / "memory").iterdir())
    assert names == sorted(p.name for p in (tmp_path / "streamed").iterdir())
    for name in names:
        assert (tmp_path / "memory" / name).read_bytes() == (tmp_path / "streamed" / name).read_bytes(), name
