"""The predictor fit of mvtex.synth.generate with its PCA basis from a subset of the training shapes
and its ridge regression over all of them, block by block: checked against closed forms
and against NumPy's SVD and least squares on the whole matrix."""

from __future__ import annotations

import numpy as np
import pytest

import mvtex.synth.predictor as synth
from mvtex.synth.predictor import fit_predictor


class _Recorded:
    """(K, n, 3) shapes readable by slice or index array, remembering the largest read."""

    def __init__(self, shapes: np.ndarray):
        self.shapes = shapes
        self.shape = shapes.shape
        self.largest_read = 0

    def __getitem__(self, key) -> np.ndarray:
        rows = self.shapes[key]
        self.largest_read = max(self.largest_read, len(rows))
        return rows


def _low_rank_model(vertices: int, rank: int, pose_dim: int, seed: int):
    """Shapes exactly affine in the pose through a rank-`rank` map: x = m0 + [p, 1] W B;
    returns the function (K, pose_dim) poses -> (K, vertices, 3) shapes."""
    rng = np.random.default_rng(seed)
    basis = rng.normal(size=(rank, vertices * 3))
    weights = rng.normal(size=(pose_dim + 1, rank))
    mean = rng.normal(size=vertices * 3)

    def shapes(poses: np.ndarray) -> np.ndarray:
        flat = mean + np.hstack([poses, np.ones((len(poses), 1))]) @ weights @ basis
        return flat.reshape(len(poses), vertices, 3)

    return shapes


def test_subset_basis_recovers_an_exact_low_rank_predictor(monkeypatch):
    # 50 training shapes, the basis from 8 of them, blocks of 7: the shapes lie in a 3-D
    # affine subspace and depend affinely on the pose, so without a penalty the fit must
    # reproduce every shape, those the basis never saw and new poses too.
    monkeypatch.setattr(synth, "_CHUNK", 7)
    model = _low_rank_model(40, rank=3, pose_dim=5, seed=1)
    rng = np.random.default_rng(2)
    poses, unseen = rng.uniform(-1.0, 1.0, size=(50, 5)), rng.uniform(-1.0, 1.0, size=(6, 5))
    recorded = _Recorded(model(poses))
    predictor = fit_predictor(recorded, poses, n_components=3, ridge=0.0, max_basis_shapes=8)
    assert predictor.components.shape == (3, 40 * 3)
    np.testing.assert_allclose(predictor.predict(poses), model(poses), atol=2e-5)
    np.testing.assert_allclose(predictor.predict(unseen), model(unseen), atol=2e-5)
    assert recorded.largest_read <= 8  # never more than the basis subset or one block


def test_chunked_normal_equations_equal_least_squares_on_the_whole_matrix(monkeypatch):
    monkeypatch.setattr(synth, "_CHUNK", 6)
    rng = np.random.default_rng(3)
    num, vertices, cap, k, ridge = 41, 30, 9, 4, 0.3
    shapes = rng.normal(size=(num, vertices, 3))
    poses = rng.uniform(-1.0, 1.0, size=(num, 4))
    recorded = _Recorded(shapes)
    predictor = fit_predictor(recorded, poses, n_components=k, ridge=ridge, max_basis_shapes=cap)
    assert recorded.largest_read <= cap
    # Random vertices coincide nowhere: the tracks are the vertices, in some order.
    assert sorted(predictor.expand) == list(range(vertices))
    # The mean is over all shapes.
    np.testing.assert_allclose(predictor.mean.reshape(-1, 3)[predictor.expand], shapes.mean(axis=0), atol=1e-12)
    # The basis: the top-k right singular vectors of the evenly spaced subset, centred on
    # its own mean (compared as a projector, which ignores signs and rotations).
    subset = shapes[np.floor(np.arange(cap) * num / cap).astype(int)].reshape(cap, -1)
    _, _, vt = np.linalg.svd(subset - subset.mean(axis=0), full_matrices=False)
    components = predictor.components.reshape(k, -1, 3)[:, predictor.expand].reshape(k, -1)
    np.testing.assert_allclose(components.T @ components, vt[:k].T @ vt[:k], atol=1e-10)
    # The regression: ridge least squares over ALL shapes' coefficients on that basis, as
    # one augmented least-squares problem (bias row unpenalized).
    coeffs = (shapes.reshape(num, -1) - shapes.reshape(num, -1).mean(axis=0)) @ components.T
    features = np.hstack([poses, np.ones((num, 1))])
    penalty_rows = np.sqrt(ridge) * np.eye(features.shape[1])[:-1]
    solution, *_ = np.linalg.lstsq(np.vstack([features, penalty_rows]),
                                   np.vstack([coeffs, np.zeros((len(penalty_rows), k))]), rcond=None)
    np.testing.assert_allclose(predictor.weights, solution, atol=1e-10)


def test_at_or_below_the_cap_the_basis_uses_every_shape():
    rng = np.random.default_rng(4)
    shapes = rng.normal(size=(12, 20, 3))
    poses = rng.uniform(-1.0, 1.0, size=(12, 3))
    capped = fit_predictor(shapes, poses, n_components=5, ridge=0.1, max_basis_shapes=12)
    plain = fit_predictor(shapes, poses, n_components=5, ridge=0.1, max_basis_shapes=10_000)
    for name in ("mean", "components", "weights", "expand"):
        np.testing.assert_array_equal(getattr(capped, name), getattr(plain, name))
    with pytest.raises(ValueError, match="max_basis_shapes"):
        fit_predictor(shapes, poses, max_basis_shapes=1)
