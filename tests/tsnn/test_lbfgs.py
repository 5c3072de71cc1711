"""The batched L-BFGS: every row reaches its own known minimum, alone or in a batch."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")


def rosenbrock(x, rows):
    """Rows of shifted, scaled Rosenbrock functions (minimum 0 at (a_r, a_r²)), elementwise
    arithmetic only, so a row's value does not depend on the other rows in the batch."""
    a = 1.0 + 0.25 * rows.to(x.dtype)
    u, v = x[:, 0], x[:, 1]
    f = (a - u) ** 2 + 10.0 * (v - u * u) ** 2
    g = torch.stack([-2 * (a - u) - 40.0 * u * (v - u * u), 20.0 * (v - u * u)], 1)
    return f, g


def test_each_row_reaches_its_minimum_and_takes_the_path_it_takes_alone():
    from mvtex.tsnn.lbfgs import minimise

    rows = 5
    x0 = torch.tensor([[-1.2, 1.0], [0.0, 0.0], [2.0, -1.0], [-0.5, 2.5], [1.5, 1.5]], dtype=torch.float64)
    batch = minimise(rosenbrock, x0, 500)
    a = 1.0 + 0.25 * np.arange(rows)
    np.testing.assert_allclose(batch.x.numpy(), np.stack([a, a * a], 1), atol=1e-5)
    assert batch.f.max() < 1e-9
    for r in range(rows):
        alone = minimise(lambda x, idx, r=r: rosenbrock(x, idx + r), x0[r:r + 1], 500)
        assert torch.equal(alone.x[0], batch.x[r]) and int(alone.iterations[0]) == int(batch.iterations[r])


def test_bounds_hold_a_coordinate_and_free_ones_still_converge():
    """min (x0 - 2)² + (x1 + 1)² on [-inf, 1] x [-3, 3]: the first coordinate ends on its
    bound, the second at its free minimum; an undefined (inf) region is backed out of."""
    from mvtex.tsnn.lbfgs import minimise

    def objective(x, rows):
        f = (x[:, 0] - 2) ** 2 + (x[:, 1] + 1) ** 2
        g = torch.stack([2 * (x[:, 0] - 2), 2 * (x[:, 1] + 1)], 1)
        return torch.where(x[:, 1] < -2.5, torch.full_like(f, torch.inf), f), g

    lower = torch.tensor([-torch.inf, -3.0], dtype=torch.float64)
    upper = torch.tensor([1.0, 3.0], dtype=torch.float64)
    result = minimise(objective, torch.tensor([[5.0, 2.9], [-4.0, -2.0]], dtype=torch.float64), 100, lower, upper)
    np.testing.assert_allclose(result.x.numpy(), [[1.0, -1.0], [1.0, -1.0]], atol=1e-7)
    assert (result.x[:, 0] <= 1.0).all()
