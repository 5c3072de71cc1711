"""`mlp`: the ensemble's forward pass and spread against NumPy, a model directory in the
stored format, and a fit that learns a closed-form field on held-out poses."""

from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("safetensors")


def numpy_members(state, poses):
    """Every member's d (E,B,n',2) written out: SiLU MLPs on standardised poses, coefficients
    times the output scale on the basis, plus the mean."""
    s = {k: v.double().numpy() for k, v in state.items()}
    z = (poses - s["pose_mean"]) / s["pose_std"]
    silu = lambda x: x / (1 + np.exp(-x))  # noqa: E731
    out = []
    for e in range(s["w1"].shape[0]):
        h = silu(z @ s["w1"][e] + s["b1"][e])
        h = silu(h @ s["w2"][e] + s["b2"][e])
        coef = (h @ s["w3"][e] + s["b3"][e]) * s["output_scale"]
        out.append((s["mean"] + coef @ s["basis"]).reshape(len(poses), -1, 2))
    return np.stack(out)


def test_model_directory_in_the_stored_format_loads_predicts_and_spreads(tmp_path):
    """A model directory written by hand with the tensors and config.json keys `mlp` models
    are stored with: `load_model` reads it (no pickle), predicts the members' mean written out
    in NumPy, and `predictive_std` is the members' per-vertex spread."""
    from safetensors.torch import save_file

    from mvtex.tsnn.modeldir import MODEL_FORMAT
    from mvtex.tsnn.predict import load_model, predict_displacements

    e, p, h, c, n = 3, 4, 6, 5, 7
    rng = np.random.default_rng(0)
    shapes = {"w1": (e, p, h), "b1": (e, 1, h), "w2": (e, h, h), "b2": (e, 1, h), "w3": (e, h, c), "b3": (e, 1, c),
              "pose_mean": (p,), "basis": (c, 2 * n), "mean": (2 * n,)}
    state = {k: torch.from_numpy(rng.normal(scale=0.5, size=v).astype(np.float32)) for k, v in shapes.items()}
    state["pose_std"] = torch.from_numpy(rng.uniform(0.5, 2, p).astype(np.float32))
    state["output_scale"] = torch.tensor(0.01)
    save_file(state, str(tmp_path / "model.safetensors"))
    meta = {"format": MODEL_FORMAT, "version": 2, "camera": "left",
            "architecture": {"arch": "mlp", "pose_dim": p, "num_vertices": n, "components": c, "hidden": h,
                             "members": e},
            "mesh": {"subdiv": 0, "num_base_vertices": n, "num_vertices": n, "base_mesh_sha256": "0" * 64}}
    (tmp_path / "config.json").write_text(json.dumps(meta))
    poses = rng.normal(size=(6, p))
    model = load_model(tmp_path)
    got = predict_displacements(model, poses, np.zeros((n, 2), np.float32))
    members = numpy_members(state, poses)
    assert got.dtype == np.float32 and got.shape == (6, n, 2)
    np.testing.assert_allclose(got, members.mean(0), rtol=1e-4, atol=1e-6)
    with torch.no_grad():
        std = model.network.predictive_std(torch.from_numpy(poses)).numpy()
    expected = np.sqrt(((members - members.mean(0)) ** 2).sum(-1).mean(0))
    np.testing.assert_allclose(std, expected, rtol=1e-4, atol=1e-6)


@pytest.mark.slow
def test_fit_learns_a_smooth_field_and_its_spread_grows_away_from_the_data():
    """Coefficients that are smooth functions of the pose: the ensemble's held-out error is
    far below predicting the training mean, each member's chosen epoch is recorded, and the
    members disagree more far outside the training poses than inside them."""
    from mvtex.tsnn.mlp import fit_pose_mlp

    rng = np.random.default_rng(1)
    n = 4
    directions = rng.normal(size=(2, 2 * n))

    def field(x):
        return (np.sin(x[:, :1]) * directions[0] + (x[:, 1:2] * x[:, 2:3]) * directions[1]).reshape(len(x), n, 2) * 0.01

    x, xv, xt = rng.uniform(-2, 2, (300, 3)), rng.uniform(-2, 2, (40, 3)), rng.uniform(-1.8, 1.8, (100, 3))
    model, history = fit_pose_mlp(x, field(x), xv, field(xv), components=4, hidden=32, members=3, seed=0,
                                  steps=600)
    assert len(history["best_epoch"]) == 3 and all(1 <= b <= len(history["val"]) for b in history["best_epoch"])
    with torch.no_grad():
        pred = model(torch.from_numpy(xt)).numpy()
        far = model.predictive_std(torch.from_numpy(rng.uniform(6, 8, (50, 3)))).mean()
        near = model.predictive_std(torch.from_numpy(xt)).mean()
    truth = field(xt)
    baseline = ((truth - field(x).mean(0)) ** 2).mean()
    assert ((pred - truth) ** 2).mean() < 0.05 * baseline
    assert far > 3 * near


def test_the_loss_history_is_the_squared_error_of_d_per_vertex():
    """The history (and so loss.png's axis) is in uv² per vertex: with one member, the
    validation value of the kept epoch is the mean over poses and vertices of |pred - d|²
    computed directly from the model's prediction (the field lies in the basis, so nothing
    is lost outside it)."""
    from mvtex.tsnn.mlp import fit_pose_mlp
    from mvtex.tsnn.modeldir import LOSS_AXIS

    rng = np.random.default_rng(4)
    n = 6
    directions = rng.normal(size=(2, 2 * n))

    def field(x):
        return (np.sin(x[:, :1]) * directions[0] + np.cos(x[:, 1:2]) * directions[1]).reshape(len(x), n, 2) * 0.01

    x, xv = rng.uniform(-2, 2, (120, 2)), rng.uniform(-2, 2, (30, 2))
    model, history = fit_pose_mlp(x, field(x), xv, field(xv), components=2, hidden=16, members=1, seed=0, steps=200)
    with torch.no_grad():
        pred = model(torch.from_numpy(xv)).double().numpy()
    direct = float(((pred - field(xv)) ** 2).sum(-1).mean())
    assert history["val"][history["best_epoch"][0] - 1] == pytest.approx(direct, rel=1e-3)
    assert LOSS_AXIS["mlp"] == "squared error of d per vertex (uv²)"
