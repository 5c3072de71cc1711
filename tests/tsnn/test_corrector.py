"""The geometry corrector and `correct`: a residual that is an exact function of the pose is
recovered; each training pose's out-of-sample prediction is the GP refitted without it
(leave-one-out, closed form written out here) or without its fold (the sparse model); σ
is calibrated on the validation poses; the corrected set is self-contained."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import grid_mesh

torch = pytest.importorskip("torch")
pytest.importorskip("safetensors")


def numpy_kernel(a, b, log_l, log_s, log_t):
    """s² exp(-½ Σ r_i²) + t² Σ_i exp(-½ r_i²), r_i = (a_i - b_i) / ℓ_i, written out."""
    r2 = ((a[:, None, :] - b[None, :, :]) / np.exp(log_l)) ** 2
    return np.exp(2 * log_s) * np.exp(-0.5 * r2.sum(-1)) + np.exp(2 * log_t) * np.exp(-0.5 * r2).sum(-1)


def residual_fields(rest):
    """Three smooth 3-D fields on the sheet (n,3): the shapes the residual is made of."""
    x, y = rest[:, 0] / 0.3, rest[:, 1] / 0.3
    return np.stack([np.stack([0 * x, 0 * x, np.sin(3 * x)], 1), np.stack([np.cos(2 * y), 0 * x, 0.5 * x * y], 1),
                     np.stack([0 * x, np.sin(2 * x + y), np.cos(3 * y)], 1)])


def truth(theta):
    """The residual's coefficients (K,3): smooth functions of the 2-D pose."""
    return np.stack([np.sin(1.5 * theta[:, 0]), theta[:, 1] ** 2 - 0.3, np.sin(theta[:, 0]) * np.cos(theta[:, 1])], 1)


@pytest.fixture(scope="module")
def posed_sheet(tmp_path_factory):
    """56 poses of the sheet: inferred a pose-dependent wave, gt = inferred + a residual that
    is an exact function of the pose (3 fields, ~5 mm), train 40 / val 8 / test 8."""
    from mvtex.data.dataset import save_dataset

    faces, uv, rest = grid_mesh(12, 10, size=0.6)
    rng = np.random.default_rng(0)
    theta = rng.uniform(-1.5, 1.5, (56, 2))
    inferred = rest[None] + np.stack([np.zeros_like(rest)] * 56)
    inferred[:, :, 2] = 0.01 * np.sin(6 * rest[None, :, 0] + theta[:, :1])
    residual = 0.004 * np.einsum("kc,cnd->knd", truth(theta), residual_fields(rest))
    split = {"train": list(range(40)), "val": list(range(40, 48)), "test": list(range(48, 56))}
    path = tmp_path_factory.mktemp("posed") / "sheet"
    save_dataset(path, faces=faces, uv=uv, gt=inferred + residual, inferred=inferred, poses=theta, name="posed",
                 rest=rest, split=split)
    return path


@pytest.fixture(scope="module")
def trained(posed_sheet, tmp_path_factory):
    from mvtex.tsnn.corrector import GeometryOptions, train_geometry

    out = tmp_path_factory.mktemp("geometry") / "model"
    result = train_geometry(posed_sheet, out, options=GeometryOptions(components=8, iterations=30, device="cpu"),
                            progress=False)
    return out, result


def test_a_residual_that_is_a_function_of_the_pose_is_recovered(posed_sheet, trained, tmp_path):
    """Corrected test poses (never read by the fit) are within 3 % of gt's RMSE to the
    inferred mesh; the corrected set keeps the original mesh, gt, the split and the record."""
    from mvtex.data.dataset import load_dataset
    from mvtex.tsnn.correct import correct

    model, result = trained
    assert result.out_of_sample == "leave-one-out" and result.num_poses == {"train": 40, "val": 8, "test": 8}
    out = correct(posed_sheet, model, tmp_path / "corrected", progress=False)
    assert out.out_of_sample_poses == 40 and out.has_gt
    source, fixed = load_dataset(posed_sheet), load_dataset(tmp_path / "corrected")
    assert fixed.corrected and fixed.split == source.split
    np.testing.assert_array_equal(fixed.gt, source.gt)
    np.testing.assert_array_equal(fixed.original_inferred, source.inferred)
    test = source.split["test"]
    before = np.sqrt(np.mean((np.asarray(source.gt[test]) - source.inferred[test]) ** 2))
    after = np.sqrt(np.mean((np.asarray(fixed.gt[test]) - fixed.inferred[test]) ** 2))
    assert after < 0.03 * before
    assert fixed.geometry_uncertainty.shape == (56, len(source.uv)) and np.all(fixed.geometry_uncertainty > 0)
    record = json.loads((tmp_path / "corrected" / "dataset.json").read_text())["correction"]
    assert record["source_poses"] == list(range(56)) and record["out_of_sample_poses"] == 40
    # A subset of poses: rows in the order asked, the split remapped to them.
    part = correct(posed_sheet, model, tmp_path / "part", poses=[50, 3, 44], progress=False)
    sub = load_dataset(tmp_path / "part")
    assert part.poses == 3 and sub.split == {"train": [1], "val": [2], "test": [0]}
    np.testing.assert_array_equal(sub.inferred[1], fixed.inferred[3])


def test_leave_one_out_is_the_refit_without_that_pose(posed_sheet, trained, tmp_path):
    """Each training pose's correction is the GP of its components conditioned on the other
    39 training poses, same hyperparameters (written out in NumPy: k(θ_i, Θ_-i) (K_-i +
    σ²I)⁻¹ y_-i, and its variance), mapped through the basis: what `correct` writes
    without shrinking."""
    from mvtex.data.dataset import load_dataset
    from mvtex.tsnn.correct import CorrectOptions, correct
    from mvtex.tsnn.corrector import load_corrector

    model = load_corrector(trained[0]).model
    gp = {k: v.numpy() for k, v in model.gp.state_dict().items()}
    source = load_dataset(posed_sheet)
    residual = (np.asarray(source.gt[:40], np.float64) - source.inferred[:40]).reshape(40, -1)
    y = (residual - gp["mean"]) @ gp["basis"].T  # the training coefficients (orthonormal basis)
    z = (np.asarray(source.poses[:40], np.float64) - gp["pose_mean"]) / gp["pose_std"]
    correct(source, trained[0], tmp_path / "c", poses=[0, 7, 23], options=CorrectOptions(shrink=0), progress=False)
    written = load_dataset(tmp_path / "c").inferred
    for row, i in enumerate((0, 7, 23)):
        rest = np.delete(np.arange(40), i)
        coef, var = np.zeros(len(y[0])), np.zeros(len(y[0]))
        for c in range(len(coef)):
            args = (gp["log_lengthscale"][c], gp["log_signal"][c], gp["log_additive"][c])
            noise = np.exp(2 * gp["log_noise"][c])
            if not np.any(gp["alpha"][:, c]):
                continue
            a = numpy_kernel(z[rest], z[rest], *args) + noise * np.eye(39)
            k = numpy_kernel(z[i:i + 1], z[rest], *args)[0]
            coef[c] = k @ np.linalg.solve(a, y[rest, c])
            var[c] = numpy_kernel(z[i:i + 1], z[i:i + 1], *args)[0, 0] + noise - k @ np.linalg.solve(a, k)
        kept = np.any(gp["alpha"], axis=0)
        np.testing.assert_allclose(model.oos_mean.numpy()[i, kept], coef[kept], rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(model.oos_var.numpy()[i, kept], var[kept], rtol=1e-6)
        refit = source.inferred[i] + (gp["mean"] + coef @ gp["basis"]).reshape(-1, 3)
        np.testing.assert_allclose(written[row], refit, atol=2e-7)


def test_sparse_folds_are_the_refit_without_the_fold():
    """Above the exact limit: each fold's prediction is the subset-of-regressors GP on the
    inducing poses refitted without that fold, same hyperparameters. Written out here as
    what the sparse GP is, Bayesian linear regression on the features φ(θ) = L⁻¹ k_m(θ)
    (K_mm = LLᵀ, the model's jitter): w = (Φ_-fᵀ Φ_-f + σ²I)⁻¹ Φ_-fᵀ y_-f, prediction Φ_f w,
    variance σ² + σ² φᵀ (Φ_-fᵀ Φ_-f + σ²I)⁻¹ φ (R&W eq. 8.14-8.15 in the weight view)."""
    from mvtex.tsnn.gp import fit_components
    from mvtex.tsnn.pca import pose_pca, residual_var

    rng = np.random.default_rng(2)
    theta = rng.uniform(-1.5, 1.5, (90, 2))
    values = np.einsum("kc,cnd->knd", truth(theta), rng.normal(size=(3, 7, 3))) + 0.05 * rng.normal(size=(90, 7, 3))
    pca = pose_pca(theta, values, 3)
    gp, (mean, var) = fit_components(pca, residual_var(values, *pca[3:]), 3, iterations=20, inducing=25,
                                     out_of_sample=4)
    assert gp.config.num_train == 25 and gp.config.channels == 3
    b = {k: v.numpy() for k, v in gp.state_dict().items()}
    z = (theta - b["pose_mean"]) / b["pose_std"]
    y = (values.reshape(90, -1) - b["mean"]) @ b["basis"].T
    zm = b["inputs"]
    for c in range(3):
        args = (b["log_lengthscale"][c], b["log_signal"][c], b["log_additive"][c])
        noise = np.exp(2 * b["log_noise"][c])
        kmm = numpy_kernel(zm, zm, *args)
        chol = np.linalg.cholesky(kmm + 1e-8 * kmm.diagonal().mean() * np.eye(25))
        phi = np.linalg.solve(chol, numpy_kernel(zm, z, *args)).T  # (K,M)
        for f in range(4):
            held = np.arange(f, 90, 4)
            kept = np.setdiff1d(np.arange(90), held)
            s = phi[kept].T @ phi[kept] + noise * np.eye(25)
            w = np.linalg.solve(s, phi[kept].T @ y[kept, c])
            np.testing.assert_allclose(mean[held, c], phi[held] @ w, rtol=1e-6, atol=1e-9 * np.abs(y[:, c]).max())
            expected = noise + noise * np.einsum("fm,fm->f", phi[held], np.linalg.solve(s, phi[held].T).T)
            np.testing.assert_allclose(var[held, c], expected, rtol=1e-6)


def test_the_correction_shrinks_where_the_corrector_is_unsure():
    """f = ‖r‖² / (‖r‖² + κσ²) per vertex and σ' = sqrt(σ² + (1 - f)²‖r‖²), written out;
    κ = 0 keeps everything."""
    from mvtex.tsnn.correct import shrink_correction

    rng = np.random.default_rng(4)
    r, sigma = rng.normal(scale=0.003, size=(2, 50, 3)), rng.uniform(0.001, 0.006, (2, 50))
    r[0, 0] = 0.0
    kept, sig = shrink_correction(r, sigma, 0.25)
    for b in range(2):
        for i in range(50):
            n2 = float(r[b, i] @ r[b, i])
            f = n2 / (n2 + 0.25 * sigma[b, i] ** 2) if n2 > 0 else 1.0
            np.testing.assert_allclose(kept[b, i], f * r[b, i], rtol=1e-12, atol=1e-18)
            assert sig[b, i] == pytest.approx(np.sqrt(sigma[b, i] ** 2 + (1 - f) ** 2 * n2), rel=1e-12)
    same, same_sigma = shrink_correction(r, sigma, 0.0)
    assert same is r and same_sigma is sigma


def test_sigma_is_calibrated_on_the_validation_poses(posed_sheet, trained):
    """On the validation poses the mean squared error of the corrected vertices equals their
    mean predicted variance (both computed here from gt and the model's σ)."""
    from mvtex.data.dataset import load_dataset
    from mvtex.tsnn.corrector import load_corrector

    loaded = load_corrector(trained[0])
    source = load_dataset(posed_sheet)
    val = source.split["val"]
    residual, sigma, in_sample = loaded.model.predict(np.asarray(source.poses[val]))
    assert not in_sample.any()
    err2 = np.sum((np.asarray(source.inferred[val]) + residual - source.gt[val]) ** 2, axis=2)
    assert np.mean(err2) / np.mean(sigma ** 2) == pytest.approx(1.0, rel=1e-6)
    assert trained[1].sigma_scale == pytest.approx(float(loaded.model.sigma_scale))


def test_correct_refuses_another_mesh_and_a_per_camera_model(posed_sheet, trained, tmp_path):
    """A model made for another mesh: one InputError naming its config.json, nothing written."""
    from mvtex.data.dataset import save_dataset
    from mvtex.tsnn.correct import correct
    from mvtex.tsnn.corrector import load_corrector
    from mvtex.util.errors import InputError

    faces, uv, rest = grid_mesh(8, 8)
    other = tmp_path / "other"
    save_dataset(other, faces=faces, uv=uv, gt=np.stack([rest] * 4), inferred=np.stack([rest] * 4),
                 poses=np.zeros((4, 2)))
    with pytest.raises(InputError, match="made for another mesh") as err:
        correct(other, trained[0], tmp_path / "out", progress=False)
    assert str(err.value.path).endswith("config.json") and not (tmp_path / "out").exists()
    fake = tmp_path / "camera_model"
    fake.mkdir()
    (fake / "config.json").write_text(json.dumps({"format": "mvtex-tsnn", "version": 3}))
    with pytest.raises(InputError, match="not a geometry model"):
        load_corrector(fake)


@pytest.mark.gl
def test_the_command_line_path_reports_against_the_corrected_and_the_original_mesh(tiny_dataset, rig_file, gl,
                                                                                   tmp_path, capsys):
    """train --geometry, correct, slide on the corrected set, eval and triangulate: both
    report the mesh before the correction too, with the errors computed here from the
    files (the original mesh's RMSE to gt; its material error is eval's baseline on the
    source dataset, the same images)."""
    from helpers import run, run_json

    from mvtex.data.dataset import load_dataset

    geometry = run_json(capsys, "train", tiny_dataset, "--geometry", "--out", tmp_path / "geom", "--components", 3,
                        "--device", "cpu", "--quiet")
    assert geometry["num_poses"]["train"] == 4 and geometry["out_of_sample"] == "leave-one-out"
    code, _, err = run(capsys, "train", tiny_dataset, "--geometry", "--texcoords", tmp_path, "--out", tmp_path / "x")
    assert code == 2 and "does not apply to --geometry" in err
    fixed = run_json(capsys, "correct", tiny_dataset, "--model", tmp_path / "geom", "--out", tmp_path / "c",
                     "--quiet")
    assert fixed["poses"] == 6 and fixed["out_of_sample_poses"] == 4
    code, _, err = run(capsys, "slide", tmp_path / "c", "--rig", rig_file, "--out", tmp_path / "ts", "--poses", "0,5",
                       "--subdiv", 0, "--workers", 1, "--quiet")
    assert code == 0, err
    evaluation = run_json(capsys, "eval", tmp_path / "c", "--rig", rig_file, "--texcoords", tmp_path / "ts", "--quiet")
    code, _, err = run(capsys, "slide", tiny_dataset, "--rig", rig_file, "--out", tmp_path / "ts0", "--poses", "0,5",
                       "--subdiv", 0, "--workers", 1, "--quiet")
    assert code == 0, err
    before = run_json(capsys, "eval", tiny_dataset, "--rig", rig_file, "--texcoords", tmp_path / "ts0", "--quiet")
    original = evaluation["original_inferred"]
    assert original["material_rmse_m"]["mean"] == pytest.approx(before["material_rmse_m"]["inferred"]["mean"],
                                                                rel=1e-6)
    assert original["ratio_material"] == pytest.approx(
        original["material_rmse_m"]["mean"] / evaluation["material_rmse_m"]["texcoords"]["mean"])
    report = run_json(capsys, "triangulate", tmp_path / "c", "--rig", rig_file, "--texcoords", tmp_path / "ts",
                      "--pose", 5, "--out", tmp_path / "rec", "--quiet")
    source, corrected = load_dataset(tiny_dataset), load_dataset(tmp_path / "c")
    gt = np.asarray(source.gt[5], np.float64)
    assert report["original_inferred"]["rmse_m"] == pytest.approx(
        np.sqrt(np.mean(np.sum((np.asarray(source.inferred[5], np.float64) - gt) ** 2, axis=1))), rel=1e-9)
    assert report["rmse_m"]["inferred"] == pytest.approx(
        np.sqrt(np.mean(np.sum((np.asarray(corrected.inferred[5], np.float64) - gt) ** 2, axis=1))), rel=1e-9)
