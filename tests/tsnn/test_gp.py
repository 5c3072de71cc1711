"""`gp`: the batched likelihood and fit against closed forms and an independent optimiser,
determinism, and a model directory in the stored format."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("safetensors")


def numpy_kernel(a, b, log_l, log_s, log_t):
    """s² exp(-½ Σ r_i²) + t² Σ_i exp(-½ r_i²), r_i = (a_i - b_i) / ℓ_i, written out."""
    r2 = ((a[:, None, :] - b[None, :, :]) / np.exp(log_l)) ** 2
    return np.exp(2 * log_s) * np.exp(-0.5 * r2.sum(-1)) + np.exp(2 * log_t) * np.exp(-0.5 * r2).sum(-1)


def numpy_nll(z, y, row):
    """½ yᵀA⁻¹y + ½ log|A|, A = K + (σ² + 1e-6) I, of one parameter row [log ℓ, log s, log σ, log t]."""
    p = z.shape[1]
    a = numpy_kernel(z, z, row[:p], row[p], row[p + 2]) + (np.exp(2 * row[p + 1]) + 1e-6) * np.eye(len(z))
    return 0.5 * y @ np.linalg.solve(a, y) + 0.5 * np.linalg.slogdet(a)[1]


TRUTHS = (
    lambda z: np.sin(1.5 * z[:, 0]),  # coordinate 0 alone
    lambda z: z[:, 1] ** 2,  # coordinate 1 alone
    lambda z: np.sin(z[:, 0]) * np.cos(z[:, 2]),  # 0 and 2 together
)


@pytest.fixture(scope="module")
def problem():
    """60 poses in 3 coordinates and three unit-variance targets, smooth functions of one
    or two coordinates plus a little noise; 200 held-out poses with the noise-free truth."""
    rng = np.random.default_rng(0)
    z, z_test = rng.uniform(-2, 2, (60, 3)), rng.uniform(-1.8, 1.8, (200, 3))
    raw = np.stack([f(z) for f in TRUTHS]) + 0.01 * rng.normal(size=(3, 60))
    mean, std = raw.mean(1, keepdims=True), raw.std(1, keepdims=True)
    truth = (np.stack([f(z_test) for f in TRUTHS]) - mean) / std
    return z, (raw - mean) / std, z_test, truth


def test_likelihood_and_gradient_against_numpy_and_finite_differences(monkeypatch):
    """The batched closed-form NLL against NumPy's solve and slogdet, its gradient against
    central differences of that NumPy NLL; tiles small enough that the covariance is built
    from many (each off-diagonal one standing for its transpose). A row below a bound acts
    at the bound with no gradient in that coordinate."""
    import mvtex.tsnn.gp_kernel as G

    monkeypatch.setattr(G, "TILE_ELEMENTS", 3 * 4 * 7 * 7)  # 7 x 7 tiles of 37 poses
    rng = np.random.default_rng(1)
    z, y = rng.normal(size=(37, 4)), rng.normal(size=(3, 37))
    params = rng.normal(scale=0.4, size=(3, 7))
    params[0, 1] = -3.0  # below the lengthscale floor
    nll, grad = G.negative_log_likelihood(torch.from_numpy(z), torch.from_numpy(y), torch.from_numpy(params))
    lo, hi = (b.numpy() for b in G.bounds(4, "cpu"))
    for r in range(3):
        at = np.clip(params[r], lo, hi)
        assert float(nll[r]) == pytest.approx(numpy_nll(z, y[r], at), rel=1e-10)
        for j in range(7):
            if not lo[j] <= params[r, j] <= hi[j]:
                assert float(grad[r, j]) == 0.0
                continue
            h = np.zeros(7)
            h[j] = 1e-5
            numeric = (numpy_nll(z, y[r], at + h) - numpy_nll(z, y[r], at - h)) / 2e-5
            assert float(grad[r, j]) == pytest.approx(numeric, rel=1e-5, abs=1e-6)


@pytest.mark.slow
def test_batched_fit_is_the_component_by_component_fit(problem):
    """All components at once give each component the optimum it reaches alone. The rows of
    a batch are independent computations; only the order of some sums differs with the
    batch size (the tile shapes), a rounding difference that L-BFGS carries along its path
    but that cannot move it off the optimum: the likelihoods agree to 1e-9 of their size, and
    parameters agree to 1e-5 (in log units, a relative 1e-5 of a lengthscale) except along
    a direction where the likelihood is flat (a noise far below the signal), where moving
    the parameter alone changes the likelihood by less than that."""
    from mvtex.tsnn.gp import _fit_hyperparameters
    from mvtex.tsnn.gp_kernel import negative_log_likelihood

    z, y, _, _ = problem
    zt, yt = torch.from_numpy(z), torch.from_numpy(y)
    together = _fit_hyperparameters(zt, yt, 60)
    for c in range(len(y)):
        alone = _fit_hyperparameters(zt, yt[c:c + 1], 60)

        def nll(params):
            return float(negative_log_likelihood(zt, yt[c:c + 1], params.reshape(1, -1))[0][0])

        f_together, f_alone = nll(together[c]), nll(alone[0])
        assert f_together == pytest.approx(f_alone, rel=1e-9)
        for j in np.flatnonzero(np.abs(together[c].numpy() - alone[0].numpy()) > 1e-5):
            # a parameter that differs is one the likelihood does not see: moving it alone
            # to the other fit's value leaves the likelihood where it was
            moved = together[c].clone()
            moved[j] = alone[0, j]
            assert nll(moved) == pytest.approx(f_together, rel=1e-9), (c, j)


@pytest.mark.slow
def test_fit_finds_the_optimum_an_independent_optimiser_finds_and_the_closed_form(problem):
    """Against SciPy's L-BFGS-B on the NumPy likelihood from the same start (central
    finite-difference gradients, the same bounds), on the target where two coordinates
    interact: the same optimum (likelihood to 1e-5 nats, held-out predictions to 1e-4 of
    the targets' spread). Against the closed form: the held-out truth to a few per cent,
    and the lengthscales say which coordinates each target depends on."""
    from scipy.optimize import minimize

    from mvtex.tsnn.gp import _fit_hyperparameters, _posterior, _start
    from mvtex.tsnn.gp_kernel import bounds, kernel_matrix

    z, y, z_test, truth = problem
    zt, yt = torch.from_numpy(z), torch.from_numpy(y)
    params = _fit_hyperparameters(zt, yt, 100)
    alpha = _posterior(zt, yt, params).numpy()
    k = kernel_matrix(torch.from_numpy(z_test), zt, params[:, :3], params[:, 3], params[:, 5]).numpy()
    predicted = np.einsum("cbk,ck->cb", k, alpha)
    assert np.sqrt(np.mean((predicted - truth) ** 2, 1)).max() < 0.05
    params = params.numpy()
    lengthscale = np.exp(params[:, :3])
    assert lengthscale[0, 0] * 3 < lengthscale[0, 1:].min()  # sin(1.5 z0): z1, z2 irrelevant
    assert lengthscale[1, 1] * 3 < lengthscale[1, [0, 2]].min()  # z1²
    assert lengthscale[2, 1] > 3 * lengthscale[2, [0, 2]].max()  # sin(z0) cos(z2): z1 irrelevant
    lo, hi = (b.numpy() for b in bounds(3, "cpu"))
    scipy = minimize(lambda q: numpy_nll(z, y[2], q), _start(1, 3, "cpu")[0].numpy(), method="L-BFGS-B",
                     jac="3-point", bounds=list(zip(np.maximum(lo, -50), np.minimum(hi, 50))),
                     options={"maxiter": 500, "ftol": 1e-15, "gtol": 1e-9})
    assert numpy_nll(z, y[2], params[2]) == pytest.approx(scipy.fun, abs=1e-5)
    q = scipy.x
    a = numpy_kernel(z, z, q[:3], q[3], q[5]) + (np.exp(2 * q[4]) + 1e-6) * np.eye(len(z))
    theirs = numpy_kernel(z_test, z, q[:3], q[3], q[5]) @ np.linalg.solve(a, y[2])
    assert np.abs(predicted[2] - theirs).max() < 1e-4


def test_fit_is_deterministic(problem):
    """Two fits of the same poses and displacements, one torch thread: the same bits."""
    from mvtex.tsnn.gp import fit_pose_gp

    z, y, _, _ = problem
    rng = np.random.default_rng(2)
    d = np.einsum("ck,cn->kn", y, rng.normal(size=(3, 40))).reshape(60, 20, 2).astype(np.float32)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        a, b = (fit_pose_gp(z * 3 + 1, d, components=3, iterations=30) for _ in range(2))
    finally:
        torch.set_num_threads(threads)
    for key, value in a.state_dict().items():
        assert torch.equal(value, b.state_dict()[key]), key


def test_model_directory_in_the_stored_format_loads_and_predicts(tmp_path):
    """A model directory with the buffers and config.json keys `gp` models are stored with,
    written by hand: `load_model` reads it and predicts the posterior mean written out in
    NumPy, d = mean + Σ_c k_c(z, Θ) α_c basis_c on standardised poses."""
    from safetensors.torch import save_file

    from mvtex.tsnn.modeldir import MODEL_FORMAT
    from mvtex.tsnn.predict import load_model, predict_displacements, predict_uncertainty

    k, p, c, n = 9, 4, 3, 5
    rng = np.random.default_rng(3)
    buffers = {"pose_mean": rng.normal(size=p), "pose_std": rng.uniform(0.5, 2, p), "inputs": rng.normal(size=(k, p)),
               "log_lengthscale": rng.normal(scale=0.3, size=(c, p)), "log_signal": rng.normal(scale=0.3, size=c),
               "log_additive": rng.normal(scale=0.3, size=c) - 1, "alpha": rng.normal(size=(k, c)),
               "basis": rng.normal(size=(c, 2 * n)), "mean": rng.normal(scale=0.01, size=2 * n)}
    state = {key: torch.from_numpy(value) for key, value in buffers.items()}
    state["output_scale"] = torch.tensor(1.0)
    save_file(state, str(tmp_path / "model.safetensors"))
    meta = {"format": MODEL_FORMAT, "version": 2, "camera": "left",
            "architecture": {"arch": "gp", "pose_dim": p, "num_vertices": n, "num_train": k, "components": c},
            "mesh": {"subdiv": 0, "num_base_vertices": n, "num_vertices": n, "base_mesh_sha256": "0" * 64}}
    (tmp_path / "config.json").write_text(json.dumps(meta))
    poses = rng.normal(size=(6, p))
    got = predict_displacements(load_model(tmp_path), poses, np.zeros((n, 2), np.float32))
    b = buffers
    zq = (poses - b["pose_mean"]) / b["pose_std"]
    coef = np.stack([numpy_kernel(zq, b["inputs"], b["log_lengthscale"][i], b["log_signal"][i], b["log_additive"][i])
                     @ b["alpha"][:, i] for i in range(c)], 1)
    expected = (b["mean"] + coef @ b["basis"]).reshape(6, n, 2)
    assert got.dtype == np.float32 and got.shape == (6, n, 2)
    np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-7)
    assert math.isfinite(float(np.abs(got).max()))
    # Stored without noise levels (written before they existed): no uncertainty to report.
    assert predict_uncertainty(load_model(tmp_path), poses, np.zeros((n, 2), np.float32)) is None
    # A gain multiplies every prediction; one outside [0, 1] is refused, naming the key.
    (tmp_path / "config.json").write_text(json.dumps(meta | {"gain": 0.25}))
    gained = predict_displacements(load_model(tmp_path), poses, np.zeros((n, 2), np.float32))
    np.testing.assert_allclose(gained, 0.25 * expected, rtol=1e-6, atol=1e-7)
    from mvtex.util.errors import InputError

    for bad in (1.5, -0.1, "half"):
        (tmp_path / "config.json").write_text(json.dumps(meta | {"gain": bad}))
        with pytest.raises(InputError, match="gain"):
            load_model(tmp_path)


def test_predictive_std_is_the_closed_form_posterior_variance(problem):
    """The per-vertex predictive standard deviation against the GP posterior variance
    written out in NumPy from the fitted hyperparameters (k(θ,θ) - k(θ,Θ) A⁻¹ k(Θ,θ) + σ²
    per component, A = K + σ² I; the prior variance for a component predicted as 0),
    propagated through the basis, plus the truncation residual computed from an
    independent SVD of the training displacements."""
    from mvtex.tsnn.gp import fit_pose_gp

    z, y, z_test, _ = problem
    rng = np.random.default_rng(5)
    n = 30
    d = np.einsum("ck,cn->kn", y, rng.normal(size=(3, 2 * n)))
    d += 0.05 * rng.normal(size=d.shape)  # spread over every direction: a truncation residual
    d = (0.01 * d).reshape(60, n, 2)
    model = fit_pose_gp(z * 2 + 1, d, components=4, iterations=30)
    assert model.has_uncertainty
    poses = z_test[:7] * 2 + 1
    got = model.predictive_std(torch.from_numpy(poses)).numpy()

    b = {k: v.numpy() for k, v in model.state_dict().items()}
    zt = (poses - b["pose_mean"]) / b["pose_std"]
    var = np.empty((len(poses), 4))
    for c in range(4):
        args = (b["log_lengthscale"][c], b["log_signal"][c], b["log_additive"][c])
        noise = np.exp(2 * b["log_noise"][c])
        prior = np.diag(numpy_kernel(zt, zt, *args)) + noise
        if np.any(b["alpha"][:, c] != 0):
            a = numpy_kernel(b["inputs"], b["inputs"], *args) + noise * np.eye(len(z))
            ks = numpy_kernel(zt, b["inputs"], *args)
            var[:, c] = prior - np.einsum("bk,kb->b", ks, np.linalg.solve(a, ks.T))
        else:
            var[:, c] = prior
    flat = d.reshape(60, -1)
    centred = flat - flat.mean(0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    residual = centred - centred @ vt[:4].T @ vt[:4]
    per_coordinate = var @ vt[:4] ** 2 + np.mean(residual ** 2, 0)
    expected = np.sqrt(per_coordinate.reshape(len(poses), n, 2).sum(-1))
    np.testing.assert_allclose(got, expected, rtol=1e-6)
    # The noise levels are the fit's, in coefficient units: a noise-free training pose is
    # predicted within about the noise of its component.
    assert np.all(got > 0) and np.all(np.sqrt(np.mean(residual ** 2, 0).reshape(n, 2).sum(-1)) < got)


@pytest.mark.slow
def test_predictive_std_is_calibrated_on_held_out_poses(problem):
    """On held-out poses the squared error of the predicted displacement averages about
    the predicted variance (a GP whose hyperparameters fit the data is calibrated): the
    mean of error² / std² over held-out vertices lies within a factor 2 of 1."""
    from mvtex.tsnn.gp import fit_pose_gp

    z, y, _, _ = problem
    rng = np.random.default_rng(6)
    basis = rng.normal(size=(3, 40))
    zz = rng.uniform(-2, 2, (140, 3))
    coef = np.stack([f(zz) for f in TRUTHS]) + 0.05 * rng.normal(size=(3, 140))
    d = (0.01 * (coef.T @ basis)).reshape(140, 20, 2)
    model = fit_pose_gp(zz[:100], d[:100], components=3, iterations=40)
    with torch.no_grad():
        pred = model(torch.from_numpy(zz[100:])).numpy().astype(np.float64)
    std = model.predictive_std(torch.from_numpy(zz[100:])).numpy()
    err2 = ((pred - d[100:]) ** 2).sum(-1)
    assert 0.5 < np.mean(err2) / np.mean(std ** 2) < 2.0


def test_inducing_posterior_against_the_closed_form_and_the_exact_gp():
    """The subset-of-regressors weights against NumPy's solve of (σ²K_mm + K_mk K_km) α =
    K_mk y (R&W eq. 8.14) with the kernel written out; with every pose inducing, its
    prediction is the exact GP's posterior mean k(θ,Θ)(K + σ²I)⁻¹y."""
    import mvtex.tsnn.gp as G

    rng = np.random.default_rng(3)
    z, y = rng.normal(size=(50, 3)), rng.normal(size=(2, 50))
    params = np.array([[0.2, 0.4, 0.1, 0.0, math.log(0.3), -1.0], [0.5, 0.0, 0.3, -0.2, math.log(0.5), -2.0]])
    inducing = np.arange(0, 50, 3)
    alpha = G._inducing_alpha(torch.from_numpy(z), torch.from_numpy(y), torch.from_numpy(params),
                              torch.from_numpy(inducing)).numpy()
    z_test = rng.normal(size=(20, 3))
    for c, row in enumerate(params):
        noise = np.exp(2 * row[4]) + 1e-6
        kmk = numpy_kernel(z[inducing], z, row[:3], row[3], row[5])
        kmm = numpy_kernel(z[inducing], z[inducing], row[:3], row[3], row[5])
        expected = np.linalg.solve(noise * kmm + kmk @ kmk.T, kmk @ y[c])
        k_test = numpy_kernel(z_test, z[inducing], row[:3], row[3], row[5])
        np.testing.assert_allclose(k_test @ alpha[c], k_test @ expected, rtol=0, atol=1e-5)
    every = G._inducing_alpha(torch.from_numpy(z), torch.from_numpy(y), torch.from_numpy(params),
                              torch.arange(50)).numpy()
    for c, row in enumerate(params):
        a = numpy_kernel(z, z, row[:3], row[3], row[5]) + (np.exp(2 * row[4]) + 1e-6) * np.eye(50)
        k_test = numpy_kernel(z_test, z, row[:3], row[3], row[5])
        np.testing.assert_allclose(k_test @ every[c], k_test @ np.linalg.solve(a, y[c]), rtol=0, atol=1e-5)


@pytest.mark.slow
def test_fit_above_the_exact_limit_uses_every_pose_and_reports_progress():
    """With fewer inducing poses than training poses the model is a kernel expansion on the
    evenly spaced inducing poses, closer to the noise-free truth on held-out poses than the
    exact GP fitted on those poses alone; the progress callback moves and ends at its total."""
    import mvtex.tsnn.gp as G
    from mvtex.tsnn.pca import evenly_spaced

    rng = np.random.default_rng(4)
    big = rng.uniform(-2, 2, (240, 3))
    targets = np.stack([f(big) for f in TRUTHS]) + 0.01 * rng.normal(size=(3, 240))
    d = np.stack([targets.T, 0.5 * targets.T], -1)  # (K, n'=3, 2): each vertex one truth
    calls = []
    model = G.fit_pose_gp(big, d, components=3, iterations=15, inducing=60,
                          progress=lambda done, total: calls.append((done, total)))
    assert model.config.num_train == 60
    np.testing.assert_allclose(model.inputs.numpy(), ((big - big.mean(0)) / big.std(0))[evenly_spaced(240, 60)])
    assert len(calls) > 3 and calls[-1][0] == calls[-1][1] > 0
    assert all(b[0] >= a[0] for a, b in zip(calls, calls[1:]))
    subset = G.fit_pose_gp(big[evenly_spaced(240, 60)], d[evenly_spaced(240, 60)], components=3, iterations=15)
    test_poses = rng.uniform(-1.8, 1.8, (200, 3))
    true_d = np.stack([np.stack([f(test_poses) for f in TRUTHS]).T, 0.5 * np.stack([f(test_poses) for f in TRUTHS]).T], -1)
    with torch.no_grad():
        err_all = float(((model(torch.from_numpy(test_poses)).numpy() - true_d) ** 2).mean())
        err_subset = float(((subset(torch.from_numpy(test_poses)).numpy() - true_d) ** 2).mean())
    assert err_all < 0.8 * err_subset
