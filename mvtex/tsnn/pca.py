"""The principal components of per-vertex values over training poses, the representation
`gp`, `mlp` and the geometry corrector model.

Per-vertex values v (K,n,c) of K training poses (a camera's displacements d, c = 2; the
geometry residual gt - inferred, c = 3) are flattened to (K, c·n) and written as

    v(θ) = mean + Σ_k coef_k(θ) · basis_k      basis: the first C principal components

(`pose_pca`); what the C components leave of the training values, per coordinate, is
`residual_var`. The components come from at most `BASIS_POSES` evenly spaced poses, read
`_PCA_CHUNK` at a time, so a training set of thousands of poses is never held whole.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

# Training poses of at most this many are read at once when the principal components are
# projected (float64 rows of c·n values).
_PCA_CHUNK = 256


# The principal components are those of at most this many evenly spaced training poses.
BASIS_POSES = 2000


def evenly_spaced(k: int, count: int) -> np.ndarray:
    """`count` evenly spaced indices of range(k) (all of them when count >= k)."""
    return np.arange(k) if count >= k else np.unique(np.linspace(0, k - 1, count).round().astype(int))


def pose_pca(poses: np.ndarray, d, components: int, basis_poses: int = BASIS_POSES,
             progress: Callable[[int, int], None] | None = None):
    """The principal components of per-vertex values that a `PoseGP` models, and the pose
    standardisation.

    Args:
        poses: (K,P) pose vectors.
        d: (K,n,c) per-vertex values (displacements d, c = 2; a geometry residual, c = 3):
            an array, or anything that `d[rows]` (rows: an int64 index array) reads rows
            of, so a large training set is never held whole.
        components: most principal components.
        basis_poses: the components are those of at most this many evenly spaced poses;
            every pose's coefficients are projections on them (read `_PCA_CHUNK` at a time).
        progress: called with (chunks read, chunks) as the poses are read.

    Returns (x (K,P), mean_x, std_x, mean_d (c·n,), basis (C,c·n) with orthonormal rows,
    coef (K,C)); C is at most `components` and K' - 1 (K' = min(K, basis_poses)), without
    null directions.
    """
    x = np.asarray(poses, dtype=np.float64)
    k = len(x)
    if x.ndim != 2 or len(d) != k or k < 1 or len(np.shape(d)) != 3:
        raise ValueError(f"expected poses (K,P) and values (K,n,c) with K >= 1, got {x.shape} and {np.shape(d)}")
    mean_x, std_x = x.mean(0), x.std(0)
    std_x = np.where(std_x > 1e-12, std_x, 1.0)
    rows = evenly_spaced(k, basis_poses)
    chunks = [rows[i:i + _PCA_CHUNK] for i in range(0, len(rows), _PCA_CHUNK)]
    total = len(chunks) + (0 if len(rows) == k else -(-k // _PCA_CHUNK))
    y = np.empty((len(rows), int(np.prod(np.shape(d)[1:]))))
    for i, chunk in enumerate(chunks):
        y[i * _PCA_CHUNK:i * _PCA_CHUNK + len(chunk)] = np.asarray(d[chunk], dtype=np.float64).reshape(len(chunk), -1)
        if progress is not None:
            progress(i + 1, total)
    mean_d = y.mean(0)
    centred = y - mean_d
    del y
    # PCA through the (K',K') Gram matrix: K' is small, c·n is not.
    eigval, eigvec = np.linalg.eigh(centred @ centred.T)
    order = np.argsort(eigval)[::-1][: max(0, min(components, len(rows) - 1))]
    order = order[eigval[order] > 1e-12 * max(float(eigval.max(initial=0.0)), 1e-300)]
    basis = (eigvec[:, order].T @ centred) / np.sqrt(eigval[order])[:, None]
    if len(rows) == k:
        coef = centred @ basis.T
    else:
        del centred
        coef = np.empty((k, len(basis)))
        for i0 in range(0, k, _PCA_CHUNK):
            chunk = np.arange(i0, min(i0 + _PCA_CHUNK, k))
            coef[chunk] = (np.asarray(d[chunk], dtype=np.float64).reshape(len(chunk), -1) - mean_d) @ basis.T
            if progress is not None:
                progress(len(chunks) + i0 // _PCA_CHUNK + 1, total)
    return x, mean_x, std_x, mean_d, basis, coef


def pose_pca_counted(poses: np.ndarray, d, components: int,
                     progress: Callable[[int, int], None] | None = None):
    """`pose_pca` with its default basis, and how many progress steps its reading took (the
    first steps of a fit's progress, which then goes on counting from there)."""
    reads = [0]

    def reading(done: int, total: int) -> None:
        reads[0] = total
        if progress is not None:
            progress(done, total)

    return pose_pca(poses, d, components, progress=reading), reads[0]


def residual_var(d, mean_d: np.ndarray, basis: np.ndarray, coef: np.ndarray) -> np.ndarray:
    """Per coordinate (c·n,), the mean square over the training poses of what the principal
    components leave of the values d (K,n,c) (the PCA truncation residual), read
    `_PCA_CHUNK` poses at a time."""
    k = len(coef)
    total = np.zeros(len(mean_d))
    for i0 in range(0, k, _PCA_CHUNK):
        chunk = np.arange(i0, min(i0 + _PCA_CHUNK, k))
        rows = np.asarray(d[chunk], dtype=np.float64).reshape(len(chunk), -1) - mean_d
        total += ((rows - coef[chunk] @ basis) ** 2).sum(0)
    return total / max(k, 1)
