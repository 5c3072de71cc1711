"""Filling unassigned values: exact on assigned vertices, linear precision, fmm sanity."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import Delaunay

from mvtex.sliding.fill import FillSystem, fill, solve_spd


def flat_patch(n: int = 400, seed: int = 0):
    """An irregular Delaunay triangulation of the unit square in the z=0 plane."""
    rng = np.random.default_rng(seed)
    pts = np.vstack([rng.uniform(0, 1, (n, 2)), [[0, 0], [0, 1], [1, 0], [1, 1]]])
    faces = Delaunay(pts).simplices.astype(np.int32)
    positions = np.c_[pts, np.zeros(len(pts))]
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    uniq, count = np.unique(e, axis=0, return_counts=True)
    boundary = np.unique(uniq[count == 1])
    return faces, positions, boundary, rng


@pytest.mark.parametrize("method", ["harmonic", "fmm"])
def test_assigned_values_kept_bit_for_bit(method):
    faces, positions, _, rng = flat_patch()
    values = rng.normal(size=(len(positions), 2)).astype(np.float32)
    assigned = rng.uniform(size=len(positions)) < 0.3
    out = fill(faces, positions, values, assigned, method)
    assert out.dtype == np.float32
    assert np.array_equal(out[assigned].view(np.uint32), values[assigned].view(np.uint32))
    assert np.all(np.isfinite(out))
    # Filled values stay within the range of the data (maximum principle / averaging).
    assert out.min() >= values[assigned].min() - 1e-6 and out.max() <= values[assigned].max() + 1e-6


def test_harmonic_reproduces_linear_field_on_flat_patch():
    faces, positions, boundary, rng = flat_patch()
    linear = np.c_[2.0 * positions[:, 0] - 0.5 * positions[:, 1] + 0.3, 0.7 * positions[:, 1]]
    assigned = rng.uniform(size=len(positions)) < 0.15
    assigned[boundary] = True  # interior vertices are where the cotangent Laplacian is exact
    values = np.where(assigned[:, None], linear, 123.0)
    out = fill(faces, positions, values, assigned, "harmonic")
    assert np.abs(out - linear).max() < 1e-10
    # The same with a prebuilt system.
    out2 = fill(faces, positions, values, assigned, "harmonic", system=FillSystem(faces, positions))
    assert np.abs(out2 - linear).max() < 1e-10


def test_fmm_extends_constant_and_is_finite():
    faces, positions, _, rng = flat_patch()
    assigned = positions[:, 0] < 0.3
    values = np.where(assigned[:, None], [0.25, -0.5], np.nan)
    out = fill(faces, positions, values, assigned, "fmm")
    assert np.all(np.isfinite(out))
    assert np.allclose(out, [0.25, -0.5])


def test_component_without_assigned_vertex_gets_zero_and_groups_join_copies():
    faces, positions, _, rng = flat_patch(100)
    # A second, disjoint copy of the patch with nothing assigned -> zeros.
    n = len(positions)
    faces2 = np.vstack([faces, faces + n])
    positions2 = np.vstack([positions, positions + [2.0, 0, 0]])
    values = np.ones((2 * n, 1))
    assigned = np.zeros(2 * n, bool)
    assigned[:n] = True
    for method in ("harmonic", "fmm"):
        out = fill(faces2, positions2, values, assigned, method)
        assert np.all(out[n:] == 0)
    # Joined as one group per position pair, the second copy takes the first's values.
    groups = np.r_[np.arange(n), np.arange(n)]
    values = np.c_[positions2[:, 0] + 3 * positions2[:, 1]]
    out = fill(faces2, positions2 * [1, 1, 1], values, assigned, "harmonic", groups)
    assert np.allclose(out[n:], values[:n])


def test_prebuilt_system_order_gives_the_same_solution_as_a_fresh_solve():
    """The elimination order precomputed by FillSystem must not change the solution:
    compare with a dense solve of the Dirichlet problem."""
    from mvtex.sliding.fill import HARMONIC_LAPLACIAN, laplacian_matrix

    faces, positions, _, rng = flat_patch(300, seed=3)
    positions = positions + np.c_[np.zeros((len(positions), 2)), 0.1 * np.sin(5 * positions[:, 0])]
    values = rng.normal(size=(len(positions), 2))
    assigned = rng.uniform(size=len(positions)) < 0.2
    out = fill(faces, positions, values, assigned, "harmonic", system=FillSystem(faces, positions))
    L = laplacian_matrix(positions, faces, HARMONIC_LAPLACIAN).toarray()
    u, k = np.flatnonzero(~assigned), np.flatnonzero(assigned)
    expected = np.linalg.solve(L[np.ix_(u, u)], -L[np.ix_(u, k)] @ values[k])
    assert np.abs(out[u] - expected).max() < 1e-10


def _folded_strip():
    """A strip whose middle row is pushed up steeply: obtuse angles, negative cotangent weights."""
    from helpers import grid_mesh

    faces, _, rest = grid_mesh(12, 6, size=0.3)
    positions = rest.copy()
    positions[:, 2] = 0.2 * np.exp(-(rest[:, 1] / 0.02) ** 2) * np.sin(40 * rest[:, 0])
    return faces, positions


def test_cotan_laplacian_is_the_textbook_operator_without_clamp():
    from mvtex.sliding.fill import laplacian_matrix

    faces, positions = _folded_strip()
    n = len(positions)
    W = np.zeros((n, n))
    for f in faces:  # (cot α + cot β) / 2, one corner at a time
        for k in range(3):
            o, i, j = f[k], f[(k + 1) % 3], f[(k + 2) % 3]
            a, b = positions[i] - positions[o], positions[j] - positions[o]
            cot = a @ b / np.linalg.norm(np.cross(a, b))
            W[i, j] += cot / 2
            W[j, i] += cot / 2
    expected = np.diag(W.sum(axis=1)) - W
    L = laplacian_matrix(positions, faces, "cotan").toarray()
    assert np.abs(L - expected).max() < 1e-10 * np.abs(expected).max()
    assert (W < 0).any()  # the fold makes negative weights: they are kept, not clamped


def test_intrinsic_laplacian_has_nonnegative_weights_and_degenerate_faces_fall_back():
    from mvtex.sliding.fill import laplacian_matrix

    faces, positions = _folded_strip()
    L = laplacian_matrix(positions, faces, "intrinsic").toarray()
    off = L - np.diag(np.diag(L))
    assert off.max() <= 1e-12 and np.abs(L.sum(axis=1)).max() < 1e-9
    flat = positions.copy()
    flat[faces[0, 2]] = (flat[faces[0, 0]] + flat[faces[0, 1]]) / 2  # a zero-area triangle
    L = laplacian_matrix(flat, faces, "cotan")
    assert np.all(np.isfinite(L.data))


def test_one_dimensional_values_use_the_given_system():
    """A 1-D fill with `system=` solves with that system's Laplacian, not one from `positions`."""
    faces, positions, _, rng = flat_patch(200)
    stretched = positions * [3.0, 0.5, 1.0]  # another metric: other cotangent weights
    values = rng.normal(size=len(positions))
    assigned = rng.uniform(size=len(positions)) < 0.3
    expected = fill(faces, stretched, values, assigned, "harmonic")  # Laplacian of the stretched patch
    out = fill(faces, positions, values, assigned, "harmonic", system=FillSystem(faces, stretched))
    assert out.shape == values.shape
    assert np.abs(out - expected).max() < 1e-12
    assert np.abs(out - fill(faces, positions, values, assigned, "harmonic")).max() > 1e-4


def test_restricted_harmonic_fill_equals_a_dense_dirichlet_solve():
    """The fill factorises only the unknown block of the Laplacian, in the system's stored
    elimination order; a dense solve of the whole Dirichlet problem (known rows replaced by
    identity rows) with numpy must give the same values, for several assigned sets on one
    `FillSystem` and on a curved mesh with two separate parts."""
    faces, positions, _, rng = flat_patch(150, seed=3)
    positions[:, 2] = 0.2 * np.sin(3 * positions[:, 0]) * np.cos(2 * positions[:, 1])
    # A second, disjoint copy shifted away: a separate component of the Laplacian.
    n = len(positions)
    faces = np.vstack([faces, faces + n])
    positions = np.vstack([positions, positions + [2.0, 0.0, 0.0]])
    system = FillSystem(faces, positions)
    L = system.laplacian.toarray()
    for trial in range(3):
        values = rng.normal(size=(2 * n, 2))
        assigned = rng.uniform(size=2 * n) < (0.1, 0.3, 0.6)[trial]
        A = np.where(assigned[:, None], np.eye(2 * n), L)
        b = np.where(assigned[:, None], values, 0.0)
        dense = np.linalg.solve(A, b)
        out = fill(faces, positions, values, assigned, "harmonic", system=system)
        assert np.array_equal(out[assigned], values[assigned])
        np.testing.assert_allclose(out, dense, rtol=0, atol=1e-10)
        # The stored factorisation order does not change the answer of a fresh system.
        np.testing.assert_allclose(fill(faces, positions, values, assigned, "harmonic"), dense, rtol=0, atol=1e-10)


def test_lower_submatrix_matches_dense_indexing():
    faces, positions, _, rng = flat_patch(80, seed=5)
    system = FillSystem(faces, positions)
    vertices = np.sort(rng.permutation(len(positions))[:37])
    values, rows, cols = system.lower_submatrix(vertices)
    assert np.all(rows >= cols)
    dense = np.zeros((37, 37))
    np.add.at(dense, (rows, cols), values)
    np.testing.assert_array_equal(dense, np.tril(system.laplacian.toarray()[np.ix_(vertices, vertices)]))
    with pytest.raises(ValueError, match="increasing"):
        system.lower_submatrix(vertices[::-1])


def _lower(A: np.ndarray):
    rows, cols = np.nonzero(np.tril(A))
    return A[rows, cols], rows, cols


@pytest.mark.parametrize("ordered", [False, True])
def test_solve_spd_matches_dense_solve(ordered):
    """CHOLMOD's solve of a sparse SPD system (a grounded graph Laplacian), in its own order
    or in a given elimination order, equals numpy's dense solve; one and several right-hand
    sides."""
    rng = np.random.default_rng(7)
    k = 60
    W = np.triu(rng.uniform(size=(k, k)) < 0.08, 1) * rng.uniform(0.5, 2.0, (k, k))
    W = W + W.T
    A = np.diag(W.sum(axis=1) + rng.uniform(0.01, 0.1, k)) - W
    order = rng.permutation(k) if ordered else None
    b = rng.normal(size=(k, 3))
    np.testing.assert_allclose(solve_spd(_lower(A), k, b, order), np.linalg.solve(A, b), rtol=0, atol=1e-10)
    np.testing.assert_allclose(solve_spd(_lower(A), k, b[:, 0], order), np.linalg.solve(A, b[:, 0]),
                               rtol=0, atol=1e-10)


def test_solve_spd_zero_pivot_falls_back_and_keeps_cvxopt_options():
    """A nonsingular symmetric matrix whose LDL^T meets a zero pivot is still solved (SuperLU
    with pivoting); cvxopt's global CHOLMOD options are as the caller left them."""
    from cvxopt import cholmod

    A = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 2.0]])
    b = np.array([1.0, 2.0, 3.0])
    cholmod.options["supernodal"] = 2
    try:
        np.testing.assert_allclose(solve_spd(_lower(A), 3, b), np.linalg.solve(A, b), rtol=0, atol=1e-12)
        assert cholmod.options == {"supernodal": 2}
    finally:
        cholmod.options.clear()
