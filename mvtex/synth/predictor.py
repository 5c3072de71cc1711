"""The inferred meshes of the built-in datasets: a predictor *fitted* to the training
poses (PCA of the gt shapes, ridge regression from the pose), evaluated on all poses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_CHUNK = 256  # poses per block when streaming shapes to and from disk
MAX_BASIS_SHAPES = 1000  # most training shapes the predictor's PCA basis is computed from


@dataclass(frozen=True)
class PosePredictor:
    """Linear pose -> shape predictor: ridge regression onto a PCA basis of the shapes.

    Attributes:
        mean: (3t,) float64 mean shape over t distinct vertex tracks.
        components: (k, 3t) float64 orthonormal PCA components.
        weights: (P + 1, k) float64 regression weights; the last row is the bias.
        expand: (n,) int64 vertex -> distinct track (vertices that coincide in every
            training shape, like seam copies, share a track and stay coincident).
    """

    mean: np.ndarray
    components: np.ndarray
    weights: np.ndarray
    expand: np.ndarray

    def predict(self, poses: np.ndarray) -> np.ndarray:
        """Predicted shapes of (K, P) poses, (K, n, 3) float32."""
        poses = np.atleast_2d(np.asarray(poses, dtype=np.float64))
        features = np.hstack([poses, np.ones((len(poses), 1))])
        flat = self.mean + (features @ self.weights) @ self.components
        return flat.reshape(len(poses), -1, 3)[:, self.expand].astype(np.float32)


def _basis_subset(num: int, cap: int) -> np.ndarray:
    """Indices of at most `cap` of `num` shapes, evenly spaced and sorted: all of them
    (0, 1, ..., num - 1) when num <= cap, else floor(i * num / cap) for i < cap."""
    count = min(num, cap)
    return np.arange(count, dtype=np.int64) * num // count


def fit_predictor(gt_train: np.ndarray, poses_train: np.ndarray, n_components: int = 6, ridge: float = 1e-2,
                  max_basis_shapes: int = MAX_BASIS_SHAPES) -> PosePredictor:
    """Fit PCA (few components) of the shapes and ridge regression from pose to coefficients.

    With few components and a model linear in the pose, the fit cannot follow folds
    whose position and depth depend nonlinearly on the pose: its meshes are smooth and
    off in tangential material position, like a learned cloth predictor's.

    Memory does not grow with the number of training shapes K. The PCA basis is computed
    from at most `max_basis_shapes` of them (evenly spaced in training order, so
    deterministic; all of them when K <= max_basis_shapes, and then the result is the
    plain PCA of all shapes) through their small Gram matrix. The mean shape and the ridge
    regression use ALL K shapes: they are read `_CHUNK` at a time, projected onto the
    basis, and only the (P + 1) x (P + 1) and (P + 1) x k normal equations are summed, so
    no (K, 3t) float64 array exists. A few components of shapes this smooth are pinned
    down by a thousand samples; the regression, whose error is what the inferred meshes
    show, still sees every pose.

    Args:
        gt_train: (K, n, 3) training shapes: an array, or anything with `.shape` that
            returns arrays for `gt_train[a:b]` and `gt_train[index_array]` (a memory map;
            it is read in blocks, never whole).
        poses_train: (K, P) their poses.
        n_components: PCA components kept (at most min(K, max_basis_shapes) - 1 are used).
        ridge: penalty on the pose weights (not on the bias).
        max_basis_shapes: most training shapes the PCA basis is computed from (>= 2).
    """
    gt = gt_train if hasattr(gt_train, "shape") and hasattr(gt_train, "__getitem__") else np.asarray(gt_train)
    poses = np.asarray(poses_train, dtype=np.float64)
    shape = tuple(gt.shape)
    if len(shape) != 3 or shape[2] != 3 or poses.ndim != 2 or len(poses) != shape[0] or shape[0] < 1:
        raise ValueError(f"expected gt_train (K, n, 3) and poses_train (K, P), got {shape} and {poses.shape}")
    if max_basis_shapes < 2:
        raise ValueError(f"max_basis_shapes must be at least 2, got {max_basis_shapes}")
    num = shape[0]
    blocks = [(lo, min(lo + _CHUNK, num)) for lo in range(0, num, _CHUNK)]
    # Tie vertices that coincide in every training shape; candidates come from the first.
    # Kept in the shapes' own (float32) type until the distinct tracks are gathered: every
    # step before that is a comparison or an ordering, exact in either type.
    _, first, expand = np.unique(np.asarray(gt[0:1])[0], axis=0, return_index=True, return_inverse=True)
    expand = expand.reshape(-1)
    differs = np.zeros(shape[1], bool)
    for lo, hi in blocks:
        block = np.asarray(gt[lo:hi])
        differs |= np.any(block[:, first[expand]] != block, axis=(0, 2))
    untied = np.flatnonzero(differs)
    first = np.concatenate([first, untied])
    expand[untied] = len(first) - len(untied) + np.arange(len(untied))

    def tracks(rows: np.ndarray) -> np.ndarray:
        """(r, 3t) float64 distinct tracks of (r, n, 3) shapes."""
        return rows[:, first].reshape(len(rows), -1).astype(np.float64)

    subset = _basis_subset(num, max_basis_shapes)
    everything = len(subset) == num
    centred = tracks(np.asarray(gt[0:num] if everything else gt[subset]))
    subset_mean = centred.mean(axis=0)
    centred -= subset_mean  # in place: the same values as centred - mean, one array fewer
    # PCA through the small (S, S) Gram matrix: S << 3t, much faster than an SVD of the data.
    eigval, eigvec = np.linalg.eigh(centred @ centred.T)
    keep = np.argsort(eigval)[::-1][: max(0, min(n_components, len(subset) - 1))]
    keep = keep[eigval[keep] > 1e-12 * max(eigval.max(), 1e-300)]
    components = (eigvec[:, keep].T @ centred) / np.sqrt(eigval[keep])[:, None]
    features = np.hstack([poses, np.ones((num, 1))])
    penalty = ridge * np.eye(features.shape[1])
    penalty[-1, -1] = 0.0
    if everything:  # one block: the centred shapes are all in memory already
        mean = subset_mean
        normal, rhs = features.T @ features, features.T @ (centred @ components.T)
    else:
        del centred
        mean = np.zeros_like(subset_mean)
        for lo, hi in blocks:
            mean += tracks(np.asarray(gt[lo:hi])).sum(axis=0)
        mean /= num
        normal, rhs = np.zeros((features.shape[1],) * 2), np.zeros((features.shape[1], len(keep)))
        for lo, hi in blocks:
            coeffs = (tracks(np.asarray(gt[lo:hi])) - mean) @ components.T
            normal += features[lo:hi].T @ features[lo:hi]
            rhs += features[lo:hi].T @ coeffs
    weights = np.linalg.solve(normal + penalty, rhs)
    return PosePredictor(mean, components, weights, expand)
