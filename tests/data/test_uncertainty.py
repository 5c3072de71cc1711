"""A texcoord set's predictive uncertainty (`<camera>/uncertainty.npy`) is checked by one
checker wherever it is written (`predict`, `save_texcoords`) and wherever a set is read:
float32 standard deviations, finite and >= 0, as written. An uncertainty of 0 (an exact
observation) is legal and triangulates as exact."""

from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
from helpers import one_line_error, run

import mvtex
from mvtex.util.output import MARKER


def gp_model(path: Path, dataset: Path, residual_var: float) -> Path:
    """A `gp` model directory for `dataset`'s mesh, written by hand with the buffers `gp`
    models are stored with; its per-vertex residual variance is `residual_var` (negative or
    huge: a broken model whose weights are all finite)."""
    torch = pytest.importorskip("torch")
    from safetensors.torch import save_file

    from mvtex.tsnn.modeldir import MODEL_FORMAT, mesh_fingerprint

    ds = mvtex.load_dataset(dataset)
    k, p, c, n = 4, ds.poses.shape[1], 2, ds.num_vertices
    rng = np.random.default_rng(0)
    buffers = {"pose_mean": np.zeros(p), "pose_std": np.ones(p), "inputs": rng.normal(size=(k, p)),
               "log_lengthscale": np.zeros((c, p)), "log_signal": np.full(c, -3.0), "log_additive": np.full(c, -5.0),
               "alpha": np.zeros((k, c)), "basis": rng.normal(scale=1e-3, size=(c, 2 * n)), "mean": np.zeros(2 * n),
               "log_noise": np.full(c, -3.0), "residual_var": np.full(2 * n, residual_var)}
    state = {key: torch.from_numpy(value) for key, value in buffers.items()}
    state["output_scale"] = torch.tensor(1.0)
    path.mkdir(parents=True)
    save_file(state, str(path / "model.safetensors"))
    meta = {"format": MODEL_FORMAT, "version": 3, "camera": "a",
            "architecture": {"arch": "gp", "pose_dim": p, "num_vertices": n, "num_train": k, "components": c},
            "mesh": {"subdiv": 0, "num_base_vertices": n, "num_vertices": n,
                     "base_mesh": mesh_fingerprint(ds.faces, ds.uv)}}
    (path / "config.json").write_text(json.dumps(meta))
    return path


def with_uncertainty(slid: Path, out: Path, make) -> Path:
    """A copy of texcoord set `slid` whose cameras carry `make(shape)` as uncertainty.npy."""
    shutil.copytree(slid, out)
    for cam in ("a", "b"):
        shape = np.load(out / cam / "assigned.npy").shape
        value = make(shape)
        if isinstance(value, np.ndarray):
            np.save(out / cam / "uncertainty.npy", value, allow_pickle=False)
    return out


# -- writers ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("residual_var", [-1.0, 1e80])  # NaN (negative variances), inf (beyond float32)
def test_predict_refuses_an_uncertainty_that_is_no_standard_deviation(residual_var, tmp_path, tiny_dataset, capsys):
    model = gp_model(tmp_path / "model", tiny_dataset, residual_var)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no numpy overflow warning on the way either
        code, _, err = run(capsys, "predict", tiny_dataset, "--model", model, "--poses", "0:3", "--out",
                           tmp_path / "pred", "--quiet")
    one_line_error(code, err, model / "model.safetensors", "uncertainty", "train it again")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model"]


def test_save_texcoords_checks_the_uncertainty_it_writes_as_float32(tmp_path, sheet):
    faces, uv, _ = sheet
    arrays = dict(faces=faces, uv=uv, parent=np.stack([np.arange(len(uv))] * 2, axis=1), source="tsnn", subdiv=0,
                  poses=[0], displacement={"a": np.zeros((1, len(uv), 2), np.float32)},
                  assigned={"a": np.ones((1, len(uv)), bool)})
    for bad in (np.full((1, len(uv)), 1e39), np.full((1, len(uv)), -1e-3), np.full((1, len(uv)), np.nan)):
        with pytest.raises(mvtex.OptionError, match=r"uncertainty\['a'\]"):
            mvtex.save_texcoords(tmp_path / "tc", uncertainty={"a": bad}, **arrays)
    assert list(tmp_path.iterdir()) == []
    mvtex.save_texcoords(tmp_path / "tc", uncertainty={"a": np.zeros((1, len(uv)))}, **arrays)  # 0 is legal
    assert np.load(tmp_path / "tc" / "a" / "uncertainty.npy").dtype == np.dtype("<f4")


# -- readers ---------------------------------------------------------------------------------------

BAD_FILES = {
    "float16": lambda shape: np.full(shape, 0.01, np.float16),
    "float64": lambda shape: np.full(shape, 0.01, np.float64),
    "big-endian": lambda shape: np.full(shape, 0.01, ">f4"),
    "NaN": lambda shape: np.full(shape, np.nan, np.float32),
    "negative": lambda shape: np.full(shape, -0.01, np.float32),
}


@pytest.mark.parametrize("case", [*BAD_FILES, "a folder", "a broken link"])
def test_every_reader_refuses_a_bad_uncertainty_file(case, tmp_path, tiny_dataset, rig_file, slid_sheet0, capsys):
    """Commands that use the uncertainty (triangulate) and those that do not (eval) alike."""
    tc = with_uncertainty(slid_sheet0, tmp_path / "tc", BAD_FILES.get(case, lambda shape: None))
    if case == "a folder":
        (tc / "a" / "uncertainty.npy").mkdir()
    elif case == "a broken link":
        (tc / "a" / "uncertainty.npy").symlink_to(tmp_path / "nothing.npy")
    for argv in (["eval", tiny_dataset, "--rig", rig_file, "--texcoords", tc],
                 ["triangulate", tiny_dataset, "--rig", rig_file, "--texcoords", tc, "--pose", 0, "--out",
                  tmp_path / "rec"]):
        code, _, err = run(capsys, *argv, "--quiet")
        one_line_error(code, err, tc / "a" / "uncertainty.npy")
    assert not (tmp_path / "rec").exists()


def test_a_zero_uncertainty_is_an_exact_observation(tmp_path, tiny_dataset, rig_file, slid_sheet0, gl):
    """Texcoords slid from gt are exact: with an uncertainty of 0 the reconstruction is the
    plain triangulation of them (every displacement trusted), close to gt, with no
    warning."""
    exact = with_uncertainty(slid_sheet0, tmp_path / "exact", lambda shape: np.zeros(shape, np.float32))
    meta = json.loads((exact / "texcoords.json").read_text())
    meta["source"] = "tsnn"  # a model's set: its points are trusted by their uncertainty (shrink)
    (exact / "texcoords.json").write_text(json.dumps(meta))
    (exact / MARKER).unlink()
    ds, rig = mvtex.load_dataset(tiny_dataset), mvtex.load_rig(rig_file)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        zero = mvtex.triangulate_pose(ds, rig, mvtex.open_texcoords(exact), 1, None, progress=False)
    plain = mvtex.triangulate_pose(ds, rig, mvtex.open_texcoords(slid_sheet0), 1, None,
                                   mvtex.ReconOptions(use_uncertainty=False, shrink=0.0), progress=False)
    assert zero.options["shrink"] > 0 and zero.stats["mean_trust"] > 0.999
    assert zero.num_triangulated == plain.num_triangulated > 0
    assert abs(zero.rmse_m.reconstructed - plain.rmse_m.reconstructed) < 1e-9
    assert zero.rmse_triangulated_m.reconstructed < 0.3 * zero.rmse_triangulated_m.inferred
