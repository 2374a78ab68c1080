"""The shared 2-D polynomial design matrix."""

import numpy as np
import pytest

from dice_core.polynomials import polynomial_design


@pytest.mark.parametrize("degree", [0, 1, 2, 6])
def test_terms_and_exact_fit(degree, rng):
    rows, cols = np.indices((30, 40))
    x, y = cols.ravel().astype(float), rows.ravel().astype(float)
    design = polynomial_design(x, y, degree=degree)
    assert design.shape == (x.size, (degree + 1) * (degree + 2) // 2)
    assert np.abs(design).max() <= 1.0 + 1e-12  # scaled to [-1, 1]
    # any polynomial of that degree in the raw coordinates is fitted exactly
    coef = rng.normal(size=(degree + 1, degree + 1))
    values = sum(coef[i, j] * (x / 40) ** i * (y / 30) ** j
                 for i in range(degree + 1) for j in range(degree + 1 - i))
    fit, *_ = np.linalg.lstsq(design, values, rcond=None)
    np.testing.assert_allclose(design @ fit, values, atol=1e-9 * np.abs(values).max())


def test_a_block_of_points_with_the_whole_sets_scaling_has_the_whole_designs_rows():
    """A design formed a block of points at a time (the gauge's sweeps) is the whole set's, bit for bit."""
    from dice_core.polynomials import polynomial_scaling

    rows, cols = np.indices((23, 31))
    x, y = cols.ravel() + 7.0, rows.ravel() - 4.0
    whole = polynomial_design(x, y, degree=6)
    scaling = polynomial_scaling(x, y)
    blocks = [polynomial_design(x[s:s + 100], y[s:s + 100], degree=6, scaling=scaling) for s in range(0, x.size, 100)]
    np.testing.assert_array_equal(np.vstack(blocks), whole)
    assert not np.array_equal(polynomial_design(x[:100], y[:100], degree=6), whole[:100])  # its own scaling differs
