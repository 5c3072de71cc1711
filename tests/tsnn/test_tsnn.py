"""Texture sliding network: atlas images, training, checkpoints, prediction.

The texcoord sets here are written directly from a closed-form, smooth, pose-dependent
displacement field on a small two-chart mesh, so nothing depends on texture sliding.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from mvtex.data.mesh import apply_parent, subdivide
from mvtex.util.errors import InputError

torch = pytest.importorskip("torch")
pytest.importorskip("safetensors")

pytestmark = pytest.mark.gl


def two_chart_mesh(nx: int = 9, ny: int = 10):
    """Two flat grids side by side in uv (u in [0.05,0.45] and [0.55,0.95]), as two charts.

    Returns faces (m,3) int32, uv (n,2) float32, positions (n,3) float64.
    """
    xs, ys = np.linspace(0, 1, nx), np.linspace(0, 1, ny)
    X, Y = np.meshgrid(xs, ys)
    unit = np.stack([X.ravel(), Y.ravel()], axis=1)
    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    grid_faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    uv_front = unit * [0.4, 0.85] + [0.05, 0.07]
    uv_back = unit * [0.4, 0.85] + [0.55, 0.07]
    faces = np.concatenate([grid_faces, grid_faces + nx * ny]).astype(np.int32)
    uv = np.concatenate([uv_front, uv_back]).astype(np.float32)
    pos = np.concatenate([np.c_[unit * 0.4, np.zeros(nx * ny)], np.c_[unit * 0.4, np.full(nx * ny, -0.1)]])
    return faces, uv, pos


def displacement_field(pose: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """A smooth field, nonlinear in the pose, (n,2) float32, about 1e-2 uv units."""
    u, v = uv[:, 0].astype(np.float64), uv[:, 1].astype(np.float64)
    du = 0.01 * (pose[0] * np.sin(4 * np.pi * u) + 0.5 * pose[1] ** 2)
    dv = 0.01 * np.cos(3 * np.pi * v + pose[2]) * (0.5 + 0.5 * u)
    return np.stack([du, dv], axis=1).astype(np.float32)


@pytest.fixture(scope="module")
def field_data(tmp_path_factory, gl):
    """A 30-pose dataset of the two-chart mesh and a subdiv-1 texcoord set of camera 'cam'."""
    from mvtex.data.dataset import load_dataset, save_dataset
    from mvtex.data.texcoords import open_texcoords, save_texcoords

    faces, uv, pos = two_chart_mesh()
    k = 30
    poses = np.random.default_rng(3).uniform(-1, 1, (k, 3)).astype(np.float32)
    root = tmp_path_factory.mktemp("tsnn")
    positions = np.repeat(pos[None], k, 0)
    save_dataset(root / "data", faces=faces, uv=uv, gt=positions, inferred=positions, poses=poses, name="charts")
    dataset = load_dataset(root / "data")
    sub = subdivide(faces, len(uv), 1)
    uv1 = apply_parent(uv, sub.parent)
    d = np.stack([displacement_field(p, uv1) for p in poses])
    # Mark a band of vertices "extrapolated", as a slide would behind an occlusion.
    assigned = np.broadcast_to(uv1[:, 1] > 0.3, d.shape[:2]).copy()
    save_texcoords(root / "tc", faces=sub.faces, uv=uv1, parent=sub.parent, source="synthetic", subdiv=1,
                   poses=list(range(k)), displacement={"cam": d}, assigned={"cam": assigned})
    return dataset, open_texcoords(root / "tc", dataset.num_vertices), root


def test_atlas_image_of_linear_field_samples_back_exactly(gl):
    from mvtex.tsnn.atlas import AtlasSampler

    faces, uv, _ = two_chart_mesh()
    sub = subdivide(faces, len(uv), 1)
    uv1 = apply_parent(uv, sub.parent)
    # A different linear function on each chart: dilation must not mix them.
    chart = (uv1[:, 0] > 0.5).astype(np.float64)
    field = np.stack([0.3 * uv1[:, 0] - 0.2 * uv1[:, 1] + 0.1 * chart,
                      uv1[:, 0] + 0.7 * uv1[:, 1] - 2.0 * chart * uv1[:, 1]], axis=1)
    for resolution in (32, 64):
        sampler = AtlasSampler(sub.faces, uv1, resolution)
        image = sampler.to_image(field)
        assert image.shape == (resolution, resolution, 2)
        back = sampler.sample_numpy(image)
        np.testing.assert_allclose(back, field, atol=2e-5)
        # Row convention: texel (r, c) holds the field at u=(c+0.5)/R, v=(r+0.5)/R.
        r, c = np.argwhere(sampler.layout.covered)[len(np.argwhere(sampler.layout.covered)) // 2]
        u, v = (c + 0.5) / resolution, (r + 0.5) / resolution
        expected = [0.3 * u - 0.2 * v + 0.1 * (u > 0.5), u + 0.7 * v - 2.0 * (u > 0.5) * v]
        np.testing.assert_allclose(image[r, c], expected, atol=2e-5)


def test_sampling_matches_hand_bilinear(gl):
    """grid_sample at T_G against a NumPy bilinear lookup with the documented texel centres."""
    from mvtex.tsnn.atlas import AtlasSampler

    faces, uv, _ = two_chart_mesh()
    sampler = AtlasSampler(faces, uv, 16)
    image = np.random.default_rng(0).normal(size=(16, 16, 2)).astype(np.float32)
    x = uv[:, 0] * 16 - 0.5  # continuous column index: centre of column c at c
    y = uv[:, 1] * 16 - 0.5
    c0, r0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = (x - c0)[:, None], (y - r0)[:, None]
    ref = ((1 - fx) * (1 - fy) * image[r0, c0] + fx * (1 - fy) * image[r0, c0 + 1]
           + (1 - fx) * fy * image[r0 + 1, c0] + fx * fy * image[r0 + 1, c0 + 1])
    np.testing.assert_allclose(sampler.sample_numpy(image), ref, atol=1e-5)


def test_overlapping_atlas_is_refused(gl):
    from mvtex.tsnn.atlas import AtlasSampler, uv_overlap

    faces, uv, _ = two_chart_mesh()
    AtlasSampler(faces, uv, 32)  # disjoint charts are fine
    overlapping = uv.copy()
    overlapping[len(uv) // 2:, 0] -= 0.3  # the back chart now covers part of the front one
    with pytest.raises(InputError, match="overlap"):
        AtlasSampler(faces, overlapping, 32, source="mesh.npz")
    # The overlap found is where the two charts' uv rectangles intersect.
    mask = uv_overlap(gl, overlapping, faces, 64)
    centres = (np.arange(64) + 0.5) / 64
    U, V = np.meshgrid(centres, centres)
    expected = (U > 0.25) & (U < 0.45) & (V > 0.07) & (V < 0.92)
    inner = (U > 0.26) & (U < 0.44) & (V > 0.08) & (V < 0.91)
    assert mask[inner].all() and not mask[~expected].any()


@pytest.mark.slow
def test_training_beats_zero_predictor_and_checkpoint_roundtrips(field_data, tmp_path):
    from mvtex.data.texcoords import open_texcoords
    from mvtex.tsnn.predict import load_model, predict, predict_displacements
    from mvtex.tsnn.train import TrainOptions, train_camera

    dataset, tc, _ = field_data
    options = TrainOptions(arch="paper", epochs=30, resolution=32, batch_size=8, width=64, patience=100, device="cpu",
                           weight_assigned=2.0)
    result = train_camera(dataset, tc, "cam", tmp_path / "model", options, progress=False)
    meta = json.loads((tmp_path / "model" / "config.json").read_text())
    history = meta["history"]["train"]
    # The first epoch already starts from the mean displacement (the bias image), so compare
    # with the zero predictor too.
    assert history[-1] < 0.3 * history[0]
    assert result.losses["train"]["loss"] < 0.05 * result.losses["train"]["zero_loss"]
    assert (tmp_path / "model" / "loss.png").stat().st_size > 1000
    assert meta["mesh"]["subdiv"] == 1 and meta["camera"] == "cam"
    assert meta["split"] == {k: dataset.split[k] for k in ("train", "val", "test")}
    assert result.losses["test"]["loss"] < 0.1 * result.losses["test"]["zero_loss"]

    # Held-out poses: an independent computation of the error from the closed-form field.
    test = dataset.split["test"]
    model = load_model(tmp_path / "model")
    pred = predict_displacements(model, dataset.poses[test], tc.uv)
    truth = np.stack([displacement_field(dataset.poses[p], tc.uv) for p in test])
    mse = np.mean(np.sum((pred - truth) ** 2, -1))
    zero = np.mean(np.sum(truth ** 2, -1))
    assert mse < 0.1 * zero

    # Saved and loaded: bit-identical to the trained network, and predict writes that.
    again = predict_displacements(load_model(tmp_path / "model"), dataset.poses[test], tc.uv)
    assert np.array_equal(pred, again)
    out = predict(dataset, [tmp_path / "model"], tmp_path / "pred", poses=test, progress=False)
    pset = open_texcoords(out, dataset.num_vertices)
    assert pset.source == "tsnn" and pset.poses == test and pset.cameras == ["cam"] and pset.subdiv == 1
    assert np.array_equal(pset.faces, tc.faces) and np.array_equal(pset.parent, tc.parent)
    np.testing.assert_array_equal(pset.uv, tc.uv)
    assert np.array_equal(pset.displacement("cam", test[1]), pred[1])
    assert pset.assigned("cam", test[0]).all()


@pytest.mark.slow
def test_training_is_deterministic_on_cpu(field_data, tmp_path):
    from safetensors.torch import load_file

    from mvtex.tsnn.train import TrainOptions, train_camera

    dataset, tc, _ = field_data
    options = TrainOptions(arch="paper", epochs=2, resolution=16, batch_size=8, width=32, device="cpu", seed=5)
    for name in ("a", "b"):
        train_camera(dataset, tc, "cam", tmp_path / name, options, progress=False)
    a, b = load_file(tmp_path / "a" / "model.safetensors"), load_file(tmp_path / "b" / "model.safetensors")
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_bad_models_are_refused(field_data, tmp_path):
    import shutil

    from mvtex.tsnn.predict import load_model, predict
    from mvtex.tsnn.train import TrainOptions, train_camera

    dataset, tc, root = field_data
    options = TrainOptions(arch="paper", epochs=1, resolution=16, batch_size=8, width=32, device="cpu")
    train_camera(dataset, tc, "cam", tmp_path / "m1", options, progress=False)

    # A model of another subdivision level cannot share a texcoord set with it.
    shutil.copytree(tmp_path / "m1", tmp_path / "m0")
    meta = json.loads((tmp_path / "m0" / "config.json").read_text())
    meta["mesh"]["subdiv"], meta["camera"] = 0, "other"
    (tmp_path / "m0" / "config.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match="subdivision"):
        predict(dataset, [tmp_path / "m1", tmp_path / "m0"], tmp_path / "out", poses=[0], progress=False)
    with pytest.raises(InputError, match="also predicted"):
        predict(dataset, [tmp_path / "m1", tmp_path / "m1"], tmp_path / "out", poses=[0], progress=False)

    # Malformed config.json: the message names the file.
    broken = tmp_path / "broken"
    shutil.copytree(tmp_path / "m1", broken)
    meta = json.loads((broken / "config.json").read_text())
    del meta["architecture"]
    (broken / "config.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match="config.json"):
        load_model(broken)
    (broken / "config.json").write_text("{not json")
    with pytest.raises(InputError, match="config.json"):
        load_model(broken)
    meta["architecture"] = {"arch": "paper", "pose_dim": 3, "resolution": 64, "width": 32, "min_width": 8, "depth": 4}
    (broken / "config.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match="model.safetensors"):
        load_model(broken)
    assert not (tmp_path / "out").exists()


def test_texcoord_set_of_another_mesh_is_refused(field_data, tmp_path):
    from mvtex.data.texcoords import open_texcoords, save_texcoords
    from mvtex.tsnn.train import TrainOptions, train_camera

    dataset, tc, _ = field_data
    uv = tc.uv.copy()
    uv[-1] += 0.001
    save_texcoords(tmp_path / "tc", faces=tc.faces, uv=uv, parent=tc.parent, source="x", subdiv=1, poses=tc.poses,
                   displacement={"cam": np.zeros((len(tc.poses), len(uv), 2), np.float32)},
                   assigned={"cam": np.ones((len(tc.poses), len(uv)), bool)})
    with pytest.raises(InputError, match="mesh.npz"):
        train_camera(dataset, open_texcoords(tmp_path / "tc"), "cam", tmp_path / "m", TrainOptions(epochs=1),
                     progress=False)


def test_regularisation_options_train_and_roundtrip(field_data, tmp_path):
    """Pose noise and embedding dropout: validated, stored, and off in evaluation mode."""
    from mvtex.tsnn.predict import load_model, predict_displacements
    from mvtex.tsnn.train import TrainOptions, train_camera

    dataset, tc, _ = field_data
    for bad in (dict(pose_noise=-0.1), dict(dropout=1.0), dict(dropout=-0.5)):
        with pytest.raises(ValueError):
            train_camera(dataset, tc, "cam", tmp_path / "bad", TrainOptions(epochs=1, **bad), progress=False)
    options = TrainOptions(arch="paper", epochs=2, resolution=16, batch_size=8, width=32, device="cpu", pose_noise=0.2,
                           dropout=0.25)
    train_camera(dataset, tc, "cam", tmp_path / "m", options, progress=False)
    model = load_model(tmp_path / "m")
    assert model.network.config.dropout == 0.25 and not model.network.training
    # Dropout is a no-op in evaluation mode: prediction is a deterministic function of the pose.
    x = np.array(dataset.poses[:4], np.float32)  # a writable copy of the memory map
    a = predict_displacements(model, x, tc.uv)
    b = predict_displacements(model, x, tc.uv)
    assert np.array_equal(a, b)
    # ... but active in training mode, where the same input gives different outputs.
    model.network.train()
    with torch.no_grad():
        y1, y2 = model.network(torch.from_numpy(x)), model.network(torch.from_numpy(x))
    assert not torch.equal(y1, y2)


# ----------------------------------------------------------------------------- geometry U-Net


def curved_dataset(root, k: int = 24, bend: float = 1.0):
    """The two-chart mesh bent into a pose-dependent arc (front at z=0, back at z=-0.1);
    bend=0: flat in every pose."""
    from mvtex.data.dataset import load_dataset, save_dataset

    faces, uv, pos = two_chart_mesh()
    poses = np.random.default_rng(4).uniform(-1, 1, (k, 3)).astype(np.float32)
    x = pos[:, 0] - 0.2
    inferred = np.stack([pos + bend * np.c_[np.zeros(len(pos)), 0.05 * p[1] * x, 0.3 * p[0] * x ** 2]
                         for p in poses]).astype(np.float32)
    save_dataset(root, faces=faces, uv=uv, gt=inferred, inferred=inferred, poses=poses, rest=pos, name="arc")
    return load_dataset(root)


def test_geometry_images_match_exact_point_in_triangle(gl, tmp_path):
    """Position and normal channels at texel centres against an exact point-in-triangle search
    (every triangle tested, barycentrics solved in float64) on the dataset mesh."""
    from mvtex.data.mesh import barycentric_2d
    from mvtex.tsnn.atlas import AtlasSampler
    from mvtex.tsnn.geometry import geometry_images

    ds = curved_dataset(tmp_path / "d", k=3)
    sub = subdivide(ds.faces, len(ds.uv), 1)
    uv1 = apply_parent(ds.uv, sub.parent)
    r = 32
    images = geometry_images(ds, [0, 2], AtlasSampler(sub.faces, uv1, r), sub.parent)
    assert images.shape == (2, 9, r, r)
    centres = (np.arange(r) + 0.5) / r
    tri_uv = ds.uv[ds.faces].astype(np.float64)
    checked = 0
    for row in range(r):
        for col in range(r):
            point = np.array([[centres[col], centres[row]]])
            b = barycentric_2d(np.repeat(point, len(ds.faces), 0), tri_uv)
            inside = np.nonzero((b > 1e-6).all(1))[0]  # strictly inside: no tie on edges
            if len(inside) != 1:
                continue
            f = ds.faces[inside[0]]
            for k, pose in enumerate([0, 2]):
                expected = b[inside[0]] @ np.asarray(ds.inferred[pose], np.float64)[f]
                np.testing.assert_allclose(images[k, 0:3, row, col], expected, atol=2e-6)
            checked += 1
    assert checked > 200
    # Normals of the undeformed flat pose face +z (cross product of the CCW uv grid).
    flat = curved_dataset(tmp_path / "flat", k=3, bend=0.0)
    images = geometry_images(flat, [0], AtlasSampler(ds.faces, ds.uv, r), np.stack([np.arange(len(ds.uv))] * 2, 1))
    covered = AtlasSampler(ds.faces, ds.uv, r).layout.covered
    np.testing.assert_allclose(images[0, 3:6][:, covered].T, np.tile([0, 0, 1], (covered.sum(), 1)), atol=1e-6)
    np.testing.assert_allclose(images[0, 6:9][:, covered], 0, atol=1e-6)  # no strain, no curvature


def camera_field(pose: np.ndarray, uv: np.ndarray, cam_x: float) -> np.ndarray:
    """A displacement field that depends on the pose (through the shape: pose[0] bends the
    arc, pose[1] tilts it) and on the camera's x position."""
    u, v = uv[:, 0].astype(np.float64), uv[:, 1].astype(np.float64)
    du = 0.01 * (pose[0] * np.sin(4 * np.pi * u) + cam_x * v)
    dv = 0.01 * pose[1] * np.cos(3 * np.pi * v) * (0.5 + 0.5 * u)
    return np.stack([du, dv], axis=1).astype(np.float32)


@pytest.fixture(scope="module")
def rig_data(tmp_path_factory, gl):
    """The arc dataset, a 3-camera rig and a subdiv-0 texcoord set of all three cameras."""
    from mvtex.data.camera import look_at
    from mvtex.data.rig import Rig
    from mvtex.data.texcoords import open_texcoords, save_texcoords

    root = tmp_path_factory.mktemp("rig")
    ds = curved_dataset(root / "data", k=40)
    xs = {"a": -0.6, "b": 0.0, "c": 0.6}
    rig = Rig(tuple(look_at(n, (x, 0.2, 1.5), (0.2, 0.2, 0.0), width=64, height=48, focal=60) for n, x in xs.items()))
    d = {n: np.stack([camera_field(p, ds.uv, x) for p in ds.poses]) for n, x in xs.items()}
    save_texcoords(root / "tc", faces=ds.faces, uv=ds.uv, parent=np.stack([np.arange(len(ds.uv))] * 2, 1),
                   source="synthetic", subdiv=0, poses=list(range(len(ds.poses))), displacement=d,
                   assigned={n: np.ones(v.shape[:2], bool) for n, v in d.items()})
    return ds, rig, open_texcoords(root / "tc", ds.num_vertices), root


@pytest.mark.slow
def test_camera_conditioned_model_serves_a_camera_it_never_saw(rig_data, tmp_path):
    from mvtex.data.camera import look_at
    from mvtex.data.rig import Rig
    from mvtex.data.texcoords import open_texcoords
    from mvtex.tsnn.predict import load_model, predict
    from mvtex.tsnn.train import TrainOptions, train

    ds, rig, tc, _ = rig_data
    options = TrainOptions(epochs=2, resolution=16, widths=(8, 16), batch_size=8, device="cpu")
    with pytest.raises(ValueError, match="per camera"):
        train(ds, tc, tmp_path / "p", rig=rig, options=TrainOptions(arch="paper", epochs=1))
    with pytest.raises(ValueError, match="rig"):
        train(ds, tc, tmp_path / "p", options=options)
    result = train(ds, tc, tmp_path / "m", rig=rig, options=options, progress=False)
    assert result.cameras == ["a", "b", "c"] and result.camera is None
    model = load_model(tmp_path / "m")
    assert model.conditioned and sorted(model.cameras) == ["a", "b", "c"]
    meta = json.loads((tmp_path / "m" / "config.json").read_text())
    np.testing.assert_allclose(meta["cameras"]["b"], rig["b"].cam_from_world)

    novel = Rig((look_at("novel", (0.3, 0.5, 1.2), (0.2, 0.2, 0.0), width=64, height=48, focal=60),))
    test = ds.split["test"]
    out = predict(ds, [tmp_path / "m"], tmp_path / "pred", poses=test, rig=novel, progress=False)
    pred = open_texcoords(out, ds.num_vertices)
    assert pred.cameras == ["novel"]
    d = np.stack([pred.displacement("novel", p) for p in test])
    assert np.all(np.isfinite(d)) and np.abs(d).max() < 1.0
    # Without a rig the model predicts the cameras it was trained on; the view is an input,
    # so different cameras get different predictions.
    out = predict(ds, [tmp_path / "m"], tmp_path / "own", poses=test, progress=False)
    own = open_texcoords(out, ds.num_vertices)
    assert own.cameras == ["a", "b", "c"]
    assert not np.array_equal(own.displacement("a", test[0]), own.displacement("c", test[0]))


@pytest.mark.slow
def test_unet_learns_and_predicts_deterministically(rig_data, tmp_path):
    """A per-camera U-Net beats the zero predictor on held-out poses of a closed-form field;
    training twice and predicting twice give bit-identical results on the CPU."""
    from safetensors.torch import load_file

    from mvtex.tsnn.predict import load_model, predict_displacements
    from mvtex.tsnn.train import TrainOptions, train

    ds, rig, tc, _ = rig_data
    options = TrainOptions(arch="unet", epochs=40, resolution=16, widths=(8, 16), batch_size=4, device="cpu",
                           patience=100, seed=2)
    result = train(ds, tc, tmp_path / "m1", camera="b", options=options, progress=False)
    assert result.losses["test"]["loss"] < 0.7 * result.losses["test"]["zero_loss"]
    train(ds, tc, tmp_path / "m2", camera="b", options=options, progress=False)
    a, b = load_file(tmp_path / "m1" / "model.safetensors"), load_file(tmp_path / "m2" / "model.safetensors")
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)

    from mvtex.tsnn.atlas import AtlasSampler
    from mvtex.tsnn.geometry import geometry_images

    test = ds.split["test"]
    model = load_model(tmp_path / "m1")
    assert not model.conditioned and model.needs_geometry
    geo = geometry_images(ds, test, AtlasSampler(ds.faces, ds.uv, 16), np.stack([np.arange(len(ds.uv))] * 2, 1))
    x = np.array(ds.poses[test], np.float32)
    first = predict_displacements(model, x, ds.uv, geometry=geo)
    again = predict_displacements(load_model(tmp_path / "m1"), x, ds.uv, geometry=geo)
    assert np.array_equal(first, again)
    truth = np.stack([camera_field(ds.poses[p], ds.uv, 0.0) for p in test])
    assert np.mean((first - truth) ** 2) < 0.7 * np.mean(truth ** 2)


@pytest.mark.slow
def test_model_of_one_mesh_refuses_another(rig_data, tmp_path):
    from mvtex.tsnn.predict import predict
    from mvtex.tsnn.train import TrainOptions, train

    ds, rig, tc, _ = rig_data
    train(ds, tc, tmp_path / "m", rig=rig, options=TrainOptions(epochs=1, resolution=16, widths=(8, 16), device="cpu"),
          progress=False)
    # Same vertex count and faces, other uv: the fingerprint differs.
    from mvtex.data.dataset import load_dataset, save_dataset

    uv = ds.uv.copy()
    uv[:, 1] = 0.05 + 0.9 * uv[:, 1]
    save_dataset(tmp_path / "other", faces=ds.faces, uv=uv, gt=np.asarray(ds.gt), inferred=np.asarray(ds.inferred),
                 poses=np.asarray(ds.poses), name="other")
    other = load_dataset(tmp_path / "other")
    with pytest.raises(InputError, match="another mesh"):
        predict(other, [tmp_path / "m"], tmp_path / "out", poses=[0], progress=False)
    assert not (tmp_path / "out").exists()
    # A camera-conditioned model whose camera list is broken names its config.json.
    import shutil

    from mvtex.tsnn.predict import load_model

    shutil.copytree(tmp_path / "m", tmp_path / "broken")
    meta = json.loads((tmp_path / "broken" / "config.json").read_text())
    meta["cameras"]["a"] = [[1.0, 0.0]]
    (tmp_path / "broken" / "config.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match="config.json.*cameras"):
        load_model(tmp_path / "broken")


@pytest.mark.slow
def test_cli_trains_one_network_for_all_cameras_and_predicts_a_rig(rig_data, tmp_path, capsys):
    from mvtex.cli import main
    from mvtex.data.camera import look_at
    from mvtex.data.rig import Rig, save_rig
    from mvtex.data.texcoords import open_texcoords

    ds, rig, tc, root = rig_data
    save_rig(rig, tmp_path / "rig.yaml")
    args = [str(ds.path), "--texcoords", str(tc.path), "--out", str(tmp_path / "m"), "--epochs", "1",
            "--resolution", "16", "--device", "cpu", "--quiet"]
    assert main(["train", *args]) == 2  # no --rig and no TEXCOORDS/rig.yaml
    assert "rig" in capsys.readouterr().err
    assert main(["train", *args, "--rig", str(tmp_path / "rig.yaml"), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["cameras"] == ["a", "b", "c"] and summary["arch"] == "unet"
    novel = Rig((look_at("side", (-0.9, 0.3, 1.0), (0.2, 0.2, 0.0), width=64, height=48, focal=60), rig["b"]))
    save_rig(novel, tmp_path / "novel.yaml")
    assert main(["predict", str(ds.path), "--model", str(tmp_path / "m"), "--rig", str(tmp_path / "novel.yaml"),
                 "--out", str(tmp_path / "pred"), "--poses", "test", "--quiet"]) == 0
    pred = open_texcoords(tmp_path / "pred", ds.num_vertices)
    assert pred.cameras == ["side", "b"] and pred.poses == ds.split["test"]
    # The paper architecture cannot condition on a camera: a clear error, exit 2.
    assert main(["train", *args, "--rig", str(tmp_path / "rig.yaml"), "--arch", "paper"]) == 2
    assert "per camera" in capsys.readouterr().err


def test_cli_resolution_limit_is_the_training_limit(tiny_dataset, slid_sheet0, tmp_path, capsys):
    """The command line has no limit of its own: the training options' rule, in the flag's name."""
    from helpers import one_line_error, run

    from mvtex.tsnn.options import MAX_RESOLUTION, TrainOptions

    with pytest.raises(ValueError, match="^resolution must be an integer in") as raised:
        TrainOptions(resolution=2 * MAX_RESOLUTION)
    code, _, err = run(capsys, "train", tiny_dataset, "--texcoords", slid_sheet0, "--cameras", "a", "--arch", "paper",
                       "--resolution", 2 * MAX_RESOLUTION, "--out", tmp_path / "m", "--quiet")
    assert one_line_error(code, err).endswith("--" + str(raised.value))


def test_gp_loo_residuals_equal_explicit_refits():
    """The closed-form leave-one-out residuals against K explicit solves without pose i."""
    from mvtex.tsnn.gp_kernel import kernel, loo_residuals

    rng = np.random.default_rng(4)
    z = torch.from_numpy(rng.normal(size=(25, 3)))
    y = torch.from_numpy(np.sin(z[:, 0].numpy()) + 0.1 * rng.normal(size=25))
    a = kernel(z, z, torch.log(torch.tensor([0.8, 1.5, 3.0], dtype=torch.float64)),
                torch.tensor(0.2, dtype=torch.float64), torch.tensor(-1.0, dtype=torch.float64)) \
        + 0.05 * torch.eye(25, dtype=torch.float64)
    fast = loo_residuals(torch.linalg.inv(a), y).numpy()
    A, Y = a.numpy(), y.numpy()
    for i in range(25):
        rest = np.delete(np.arange(25), i)
        mean_i = A[i, rest] @ np.linalg.solve(A[np.ix_(rest, rest)], Y[rest])
        assert fast[i] == pytest.approx(Y[i] - mean_i, rel=1e-9, abs=1e-12)


@pytest.mark.slow
def test_gp_learns_the_field_roundtrips_and_is_deterministic(field_data, tmp_path):
    """`gp` (the default with a camera name) against the closed-form field on held-out poses."""
    from safetensors.torch import load_file

    from mvtex.data.texcoords import open_texcoords
    from mvtex.tsnn.predict import load_model, predict, predict_displacements
    from mvtex.tsnn.train import TrainOptions, train_camera

    dataset, tc, _ = field_data
    result = train_camera(dataset, tc, "cam", tmp_path / "a", TrainOptions(components=8), progress=False)
    assert result.arch == "gp" and (tmp_path / "a" / "relevance.png").stat().st_size > 1000
    test = dataset.split["test"]
    model = load_model(tmp_path / "a")
    pred = predict_displacements(model, dataset.poses[test], tc.uv)
    truth = np.stack([displacement_field(dataset.poses[p], tc.uv) for p in test])
    assert np.mean(np.sum((pred - truth) ** 2, -1)) < 0.1 * np.mean(np.sum(truth ** 2, -1))
    # At a training pose the posterior mean is close to the target (little noise in this field).
    p0 = dataset.split["train"][0]
    at_train = predict_displacements(model, dataset.poses[[p0]], tc.uv)[0]
    assert np.abs(at_train - tc.displacement("cam", p0)).max() < 0.1 * np.abs(tc.displacement("cam", p0)).max()
    out = predict(dataset, [tmp_path / "a"], tmp_path / "pred", poses=test, progress=False)
    assert np.array_equal(open_texcoords(out, dataset.num_vertices).displacement("cam", test[0]), pred[0])
    train_camera(dataset, tc, "cam", tmp_path / "b", TrainOptions(components=8), progress=False)
    a, b = load_file(tmp_path / "a" / "model.safetensors"), load_file(tmp_path / "b" / "model.safetensors")
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_gp_cannot_serve_every_camera(rig_data, tmp_path):
    from mvtex.tsnn.train import TrainOptions, train

    ds, rig, tc, _ = rig_data
    with pytest.raises(ValueError, match="per camera"):
        train(ds, tc, tmp_path / "m", rig=rig, options=TrainOptions(arch="gp"), progress=False)


@pytest.mark.slow
def test_cli_trains_several_cameras_side_by_side_like_one_by_one(rig_data, tmp_path, capsys):
    """`train --camera a,c --workers 2`: OUT/a and OUT/c are the models `--camera a` and
    `--camera c` write, bit for bit (gp is deterministic), and predict takes them."""
    from mvtex.cli import main
    from mvtex.data.texcoords import open_texcoords

    ds, rig, tc, root = rig_data
    base = [str(ds.path), "--texcoords", str(tc.path), "--arch", "gp", "--components", "4", "--quiet"]
    assert main(["train", *base, "--cameras", "a,c", "--workers", "2", "--out", str(tmp_path / "both"), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["cameras"] == ["a", "c"] and set(summary["models"]) == {"a", "c"}
    for cam in ("a", "c"):
        assert main(["train", *base, "--cameras", cam, "--out", str(tmp_path / cam)]) == 0
        assert (tmp_path / "both" / cam / "model.safetensors").read_bytes() == \
            (tmp_path / cam / "model.safetensors").read_bytes()
        configs = [json.loads((d / "config.json").read_text()) for d in (tmp_path / "both" / cam, tmp_path / cam)]
        for config in configs:
            config.pop("seconds")  # wall-clock time
        assert configs[0] == configs[1]
    assert main(["predict", str(ds.path), "--model", str(tmp_path / "both" / "a"), "--model",
                 str(tmp_path / "both" / "c"), "--out", str(tmp_path / "pred"), "--poses", "test", "--quiet"]) == 0
    assert open_texcoords(tmp_path / "pred", ds.num_vertices).cameras == ["a", "c"]
    capsys.readouterr()
    # --workers 2 without several cameras, and a camera the set does not have: exit 2, one line;
    # --workers 1 (the default, as a script may spell it for every command) trains the one camera.
    assert main(["train", *base, "--cameras", "a", "--workers", "2", "--out", str(tmp_path / "x")]) == 2
    assert "several cameras" in capsys.readouterr().err
    assert main(["train", *base, "--cameras", "a", "--workers", "1", "--out", str(tmp_path / "w1")]) == 0
    assert (tmp_path / "w1" / "model.safetensors").is_file()
    capsys.readouterr()
    assert main(["train", *base, "--cameras", "a,zz", "--out", str(tmp_path / "y")]) == 2
    err = capsys.readouterr().err
    assert "zz" in err and len(err.strip().splitlines()) == 1 and not (tmp_path / "y" / "a").exists()


@pytest.mark.slow
def test_predict_in_blocks_equals_one_pass(rig_data, tmp_path, monkeypatch):
    """predict writes block by block of poses; with blocks of 3 poses the set holds what one
    pass of the model over all poses gives (gp, per vertex; unet, through the atlas and the
    geometry images of each block)."""
    import mvtex.tsnn.predict as P
    from mvtex.data.texcoords import open_texcoords
    from mvtex.tsnn.train import TrainOptions, train

    ds, rig, tc, _ = rig_data
    train(ds, tc, tmp_path / "gp", camera="a", options=TrainOptions(arch="gp", components=4), progress=False)
    train(ds, tc, tmp_path / "unet", rig=rig, options=TrainOptions(arch="unet", epochs=1, resolution=16,
                                                                   device="cpu"), progress=False)
    poses = list(range(ds.num_poses))
    monkeypatch.setattr(P, "_BLOCK", 3)
    P.predict(ds, [tmp_path / "gp", tmp_path / "unet"], tmp_path / "pred", poses=poses, rig=rig, progress=False)
    out = open_texcoords(tmp_path / "pred", ds.num_vertices)
    x = np.asarray(ds.poses[poses], np.float32)
    gp = P.load_model(tmp_path / "gp")
    expected = {"a": P.predict_displacements(gp, x, out.uv)}
    unet = P.load_model(tmp_path / "unet")
    from mvtex.tsnn.atlas import AtlasSampler
    from mvtex.tsnn.geometry import geometry_images

    sampler = AtlasSampler(out.faces, out.uv, 16, dilation=int(unet.meta["atlas"]["dilation"]))
    g = geometry_images(ds, poses, sampler, out.parent)
    for cam in ("b", "c"):
        expected[cam] = P.predict_displacements(unet, x, out.uv, geometry=g, cam_from_world=rig[cam].cam_from_world)
    for cam, d in expected.items():
        got = np.stack([out.displacement(cam, k) for k in poses])
        np.testing.assert_allclose(got, d, atol=1e-6, rtol=0)
        assert all(out.assigned(cam, k).all() for k in poses)
    # gp reports its predictive uncertainty, block by block as in one pass; unet none.
    std = P.predict_uncertainty(gp, x, out.uv)
    assert std.shape == (len(poses), len(out.uv)) and np.all(std > 0)
    np.testing.assert_allclose(np.stack([out.uncertainty("a", k) for k in poses]), std, rtol=1e-6)
    assert out.has_uncertainty("a") and not out.has_uncertainty("b") and out.uncertainty("b", poses[0]) is None


def test_gp_kernel_is_ard_plus_additive_squared_exponential():
    """The kernel against the formula written out element by element."""
    from mvtex.tsnn.gp_kernel import kernel

    rng = np.random.default_rng(5)
    a, b = rng.normal(size=(4, 3)), rng.normal(size=(6, 3))
    ell, s, t = np.array([0.5, 2.0, 1.2]), 0.3, -0.7
    k = kernel(torch.from_numpy(a), torch.from_numpy(b), torch.from_numpy(np.log(ell)),
                torch.tensor(s, dtype=torch.float64), torch.tensor(t, dtype=torch.float64)).numpy()
    for i in range(4):
        for j in range(6):
            r = (a[i] - b[j]) / ell
            expected = np.exp(2 * s) * np.exp(-0.5 * r @ r) + np.exp(2 * t) * np.exp(-0.5 * r ** 2).sum()
            assert k[i, j] == pytest.approx(expected, rel=1e-12)


@pytest.mark.slow
def test_several_camera_train_keeps_finished_models_on_a_rerun(rig_data, tmp_path, capsys):
    """A rerun of `train --camera a,c` after an interruption (c's model missing) trains only
    c and leaves a's files untouched; changed options or a damaged config.json train again;
    a camera's model records what it was trained from ("inputs" in config.json)."""
    from mvtex.cli import main

    ds, rig, tc, root = rig_data
    tc_path = tmp_path / "tc"  # a copy: this test rewrites it
    shutil.copytree(tc.path, tc_path)
    out = tmp_path / "models"
    base = ["train", str(ds.path), "--texcoords", str(tc_path), "--arch", "gp", "--cameras", "a,c", "--out", str(out),
            "--quiet", "--json"]

    def stamp(cam):
        st = (out / cam / "model.safetensors").stat()
        return st.st_ino, st.st_mtime_ns

    assert main([*base, "--components", "4"]) == 0
    first = json.loads(capsys.readouterr().out)
    assert first["kept"] == []
    keys = {c: json.loads((out / c / "config.json").read_text())["inputs"] for c in ("a", "c")}
    assert keys["a"] != keys["c"]  # each camera's own targets
    a_before, c_bytes = stamp("a"), (out / "c" / "model.safetensors").read_bytes()
    shutil.rmtree(out / "c")  # a run stopped before camera c was written
    assert main([*base, "--components", "4"]) == 0
    again = json.loads(capsys.readouterr().out)
    assert again["kept"] == ["a"] and stamp("a") == a_before
    assert (out / "c" / "model.safetensors").read_bytes() == c_bytes  # gp: the same model, bit for bit
    assert again["models"]["a"]["losses"] == first["models"]["a"]["losses"]
    # Other options: both trained again.
    c_before = stamp("c")
    assert main([*base, "--components", "3"]) == 0
    assert json.loads(capsys.readouterr().out)["kept"] == [] and stamp("a") != a_before and stamp("c") != c_before
    # A damaged config.json is not trusted: that camera is trained again, the other kept.
    (out / "a" / "config.json").write_text("{")
    c_before = stamp("c")
    assert main([*base, "--components", "3"]) == 0
    assert json.loads(capsys.readouterr().out)["kept"] == ["c"] and stamp("c") == c_before
    assert json.loads((out / "a" / "config.json").read_text())["inputs"]
    # Changed targets of camera a (the texcoord set rewritten in place): a trained again.
    d = np.load(tc_path / "a" / "displacement.npy", mmap_mode="r+")
    d[0, 0, 0] += 1e-3
    d.flush()
    del d
    assert main([*base, "--components", "3"]) == 0
    assert json.loads(capsys.readouterr().out)["kept"] == ["c"]


@pytest.mark.slow
def test_mlp_learns_the_field_through_train_and_predict(field_data, tmp_path, monkeypatch):
    """`--arch mlp` through `train` and `predict`: held-out poses against the closed-form
    field, a loss plot, config.json's architecture, and every member's chosen epoch within
    the epochs run."""
    import mvtex.tsnn.mlp as M
    from mvtex.data.texcoords import open_texcoords
    from mvtex.tsnn.predict import load_model, predict, predict_displacements
    from mvtex.tsnn.train import TrainOptions, train_camera

    monkeypatch.setattr(M, "STEPS", 600)
    dataset, tc, _ = field_data
    result = train_camera(dataset, tc, "cam", tmp_path / "m", TrainOptions(arch="mlp", components=8, members=3),
                          progress=False)
    config = json.loads((tmp_path / "m" / "config.json").read_text())
    assert result.arch == "mlp" and config["architecture"]["arch"] == "mlp"
    assert config["architecture"]["members"] == 3 and (tmp_path / "m" / "loss.png").stat().st_size > 1000
    assert 1 <= config["best_epoch"] <= config["epochs_run"]
    test = dataset.split["test"]
    pred = predict_displacements(load_model(tmp_path / "m"), dataset.poses[test], tc.uv)
    truth = np.stack([displacement_field(dataset.poses[p], tc.uv) for p in test])
    mean_train = np.mean([tc.displacement("cam", p) for p in dataset.split["train"]], 0)
    assert np.mean(np.sum((pred - truth) ** 2, -1)) < 0.3 * np.mean(np.sum((truth - mean_train) ** 2, -1))
    out = predict(dataset, [tmp_path / "m"], tmp_path / "pred", poses=test, progress=False)
    assert np.array_equal(open_texcoords(out, dataset.num_vertices).displacement("cam", test[0]), pred[0])


@pytest.mark.slow
def test_unet_predicts_the_same_for_an_inference_set_of_another_rest(rig_data, tmp_path):
    """A unet measures its geometry images against the reference it was trained with
    (geometry.npz), so an inference set of the same inferred meshes and poses, whose rest is
    its first frame instead of the flat rest, gets the same d. Measured against the set's
    own rest (a model stored without geometry.npz) it would not."""
    import shutil

    from mvtex.data.dataset import save_dataset
    from mvtex.data.texcoords import open_texcoords
    from mvtex.tsnn.predict import predict
    from mvtex.tsnn.train import TrainOptions, train

    ds, rig, tc, _ = rig_data
    train(ds, tc, tmp_path / "m", rig=rig, options=TrainOptions(epochs=1, resolution=16, widths=(8, 16), device="cpu"),
          progress=False)
    assert (tmp_path / "m" / "geometry.npz").is_file()
    test = ds.split["test"]
    save_dataset(tmp_path / "frames", faces=ds.faces, uv=ds.uv, gt=None, inferred=np.asarray(ds.inferred)[test],
                 poses=np.asarray(ds.poses)[test])
    predict(ds, [tmp_path / "m"], tmp_path / "own", poses=test, rig=rig, progress=False)
    predict(tmp_path / "frames", [tmp_path / "m"], tmp_path / "new", poses=list(range(len(test))), rig=rig,
            progress=False)
    own, new = open_texcoords(tmp_path / "own"), open_texcoords(tmp_path / "new")
    diff = max(np.abs(own.displacement(c, p) - new.displacement(c, i)).max()
               for c in rig.names for i, p in enumerate(test))
    assert diff <= 1e-6
    shutil.copytree(tmp_path / "m", tmp_path / "old")
    (tmp_path / "old" / "geometry.npz").unlink()
    meta = json.loads((tmp_path / "old" / "config.json").read_text())
    del meta["geometry"]
    (tmp_path / "old" / "config.json").write_text(json.dumps(meta))
    predict(tmp_path / "frames", [tmp_path / "old"], tmp_path / "old_new", poses=list(range(len(test))), rig=rig,
            progress=False)
    old_new = open_texcoords(tmp_path / "old_new")
    assert max(np.abs(own.displacement(c, p) - old_new.displacement(c, i)).max()
               for c in rig.names for i, p in enumerate(test)) > 1e-5


def test_gain_is_the_validation_poses_least_squares_factor(field_data, tmp_path):
    """`TrainOptions.gain`: the recorded gain is Σ p·d / Σ p·p over the vertices each camera
    sees in the validation poses (p the model's prediction without the gain, d the texcoord
    set's, the sum over assigned vertices), clipped to [0, 1]; the
    model's predictions are that factor times the ungained ones. A model of d that is not a
    function of the pose gets a small gain; one of a smooth field keeps nearly all of it."""
    from mvtex.data.texcoords import open_texcoords, save_texcoords
    from mvtex.tsnn.predict import load_model, predict_displacements
    from mvtex.tsnn.train import TrainOptions, train_camera

    dataset, tc, _ = field_data
    rng = np.random.default_rng(11)
    noise = (0.01 * rng.normal(size=(dataset.num_poses, len(tc.uv), 2))).astype(np.float32)
    save_texcoords(tmp_path / "noise", faces=tc.faces, uv=tc.uv, parent=tc.parent, source="synthetic", subdiv=1,
                   poses=list(range(dataset.num_poses)), displacement={"cam": noise},
                   assigned={"cam": np.ones(noise.shape[:2], bool)})
    val = dataset.split["val"]
    for texcoords, low, high in ((open_texcoords(tmp_path / "noise", dataset.num_vertices), 0.0, 0.5),
                                 (tc, 0.9, 1.0)):
        name = texcoords.path.name
        off = train_camera(dataset, texcoords, "cam", tmp_path / f"{name}_off", TrainOptions(components=8, gain=False),
                           progress=False)
        on = train_camera(dataset, texcoords, "cam", tmp_path / f"{name}_on", TrainOptions(components=8, gain=True),
                          progress=False)
        assert off.gain is None and load_model(tmp_path / f"{name}_off").config.gain is None
        raw = predict_displacements(load_model(tmp_path / f"{name}_off"), dataset.poses[val], tc.uv).astype(np.float64)
        d = np.stack([texcoords.displacement("cam", p) for p in val]).astype(np.float64)
        seen = np.stack([texcoords.assigned("cam", p) for p in val])
        expected = float(np.clip(np.sum(raw[seen] * d[seen]) / np.sum(raw[seen] ** 2), 0.0, 1.0))
        assert low <= on.gain <= high
        assert on.gain == pytest.approx(expected, rel=1e-4, abs=1e-6)
        gained = load_model(tmp_path / f"{name}_on")
        assert gained.config.gain == on.gain
        np.testing.assert_allclose(predict_displacements(gained, dataset.poses[val], tc.uv), on.gain * raw,
                                   rtol=1e-5, atol=1e-7)


def test_gain_defaults_on_for_a_corrected_set_only():
    """`TrainOptions.gain` None: on where the dataset records a correction, off elsewhere;
    the validation gain is clipped to [0, 1]."""
    from types import SimpleNamespace

    from mvtex.tsnn.train import TrainOptions, validation_gain

    losses = {"val": {"gain": 1.4}}
    plain, corrected = SimpleNamespace(correction=None), SimpleNamespace(correction={"model": "m"})
    assert validation_gain(TrainOptions(), plain, losses) is None
    assert validation_gain(TrainOptions(), corrected, losses) == 1.0
    assert validation_gain(TrainOptions(gain=True), plain, {"val": {"gain": 0.3}}) == 0.3
    assert validation_gain(TrainOptions(gain=False), corrected, losses) is None
    assert validation_gain(TrainOptions(gain=True), plain, {"val": {"gain": -0.2}}) == 0.0


def test_sample_losses_gain_minimises_the_weighted_error():
    """`sample_losses`' gain and gain_loss (over the vertices seen) against the least squares
    written out."""
    from mvtex.tsnn.samples import sample_losses

    rng = np.random.default_rng(5)
    d = rng.normal(size=(7, 9, 2))
    w = rng.uniform(0.5, 2.0, size=(7, 9))
    seen = rng.uniform(size=(7, 9)) < 0.6
    pred = 0.6 * d + 0.3 * rng.normal(size=d.shape)
    pred[~seen] = 2.0 * d[~seen]  # the vertices not seen do not count in the gain
    data = type("Samples", (), {"d": torch.from_numpy(d), "w": torch.from_numpy(w),
                                "assigned": torch.from_numpy(seen), "__len__": lambda self: 7})()
    out = sample_losses(lambda _, idx: torch.from_numpy(pred)[idx], data, batch_size=3)
    g = np.sum(pred[seen] * d[seen]) / np.sum(pred[seen] ** 2)
    assert out["gain"] == pytest.approx(g, rel=1e-9)

    def seen_loss(gain):
        return np.mean(np.sum((gain * pred[seen] - d[seen]) ** 2, -1))

    assert out["gain_loss"] == pytest.approx(seen_loss(g), rel=1e-9)
    assert seen_loss(g) < min(seen_loss(g - 0.01), seen_loss(g + 0.01))
    assert out["loss"] == pytest.approx(np.sum(w * np.sum((pred - d) ** 2, -1)) / w.sum(), rel=1e-9)
