"""Deprojection (appendix A) against known offsets and the paper's closed form."""

import numpy as np
import pytest

import xarray as xr

from dice_core.deprojection import deproject, difference_dataset, pair_difference


def paper_closed_form(a1, k1, a2, k2):
    """Appendix A, literally: lines through P_i = a_i k_i with directions c_i = (k_yi, -k_xi)."""
    (kx1, ky1), (kx2, ky2) = (np.asarray(k) / np.hypot(*k) for k in (k1, k2))
    cx1, cy1, cx2, cy2 = ky1, -kx1, ky2, -kx2
    dx1, dy1, dx2, dy2 = kx1 * a1, ky1 * a1, kx2 * a2, ky2 * a2
    x = (cx2 * cx1 * dy2 + cy1 * cx2 * dx1 - cy2 * cx1 * dx2 - cx2 * cx1 * dy1) / (cx2 * cy1 - cx1 * cy2)
    # the paper prints y as x with the indexes switched, which is x again (see the test below);
    # eliminating x from the same two line equations gives:
    y = (cy1 * cy2 * (dx1 - dx2) - cx1 * cy2 * dy1 + cx2 * cy1 * dy2) / (cx2 * cy1 - cx1 * cy2)
    printed_y = (cx1 * cx2 * dy1 + cy2 * cx1 * dx2 - cy1 * cx2 * dx1 - cx1 * cx2 * dy2) / (cx1 * cy2 - cx2 * cy1)
    return x, y, printed_y


@pytest.mark.parametrize("k1, k2", [((2.6, 0.09), (-0.14, 2.61)), ((1.57, -0.08), (0.05, 1.57)),
                                    ((2.0, 0.0), (1.0, 1.5))])
def test_recovers_offsets_and_agrees_with_the_paper(rng, k1, k2):
    dx, dy = 1e-3 * rng.standard_normal((2, 30, 40))
    n1, n2 = (np.asarray(k) / np.hypot(*k) for k in (k1, k2))
    p1, p2 = n1[0] * dx + n1[1] * dy, n2[0] * dx + n2[1] * dy
    ex, ey = deproject(p1, k1, p2, k2)
    np.testing.assert_allclose(ex, dx, atol=1e-15)
    np.testing.assert_allclose(ey, dy, atol=1e-15)
    px, py, printed_y = paper_closed_form(p1, k1, p2, k2)
    np.testing.assert_allclose(px, dx, atol=1e-14)
    np.testing.assert_allclose(py, dy, atol=1e-14)
    # erratum: appendix A's printed y formula evaluates to x
    np.testing.assert_allclose(printed_y, px, atol=1e-14)


def test_summing_projections_is_wrong_for_non_orthogonal_baselines(rng):
    dx, dy = 1e-3 * rng.standard_normal((2, 10, 10))
    k1, k2 = (1.0, 0.0), (np.cos(1.2), np.sin(1.2))
    p1, p2 = dx, np.cos(1.2) * dx + np.sin(1.2) * dy
    summed_x = p1 * k1[0] + p2 * k2[0]
    assert np.max(np.abs(summed_x - dx)) > 1e-4
    np.testing.assert_allclose(deproject(p1, k1, p2, k2)[0], dx, atol=1e-15)


def test_colinear_wavevectors_are_refused():
    with pytest.raises(ValueError, match="pair P99: wavevectors .* colinear"):
        deproject(np.zeros(3), (2.6, 0.1), np.zeros(3), (-2.6, -0.12), label="pair P99")


def test_pair_difference_ignores_masked_pixels():
    a = np.array([[0.0, 1.0], [np.nan, 2.0]])
    ddx, ddy, sx, sy = pair_difference(a, a, a + 1, a)
    assert sx == 0.0 and sy == 0.0 and np.isnan(ddx[1, 0])


def offsets_product(dx, dy, floor, modes=None):
    """A calibration/offsets_<pair>.nc-like dataset."""
    rc = ("row", "col")
    ds = xr.Dataset({"dx": (rc, dx), "dy": (rc, dy), "dx_photon_noise_floor": (rc, np.full(dx.shape, floor)),
                     "dy_photon_noise_floor": (rc, np.full(dx.shape, 2 * floor))},
                    coords={"row": np.arange(dx.shape[0]), "col": np.arange(dx.shape[1])})
    if modes is not None:
        ds["unobservable_dx"], ds["unobservable_dy"] = (("mode", *rc), modes[0]), (("mode", *rc), modes[1])
    return ds


def test_the_difference_product_of_two_pairs(rng):
    """ddx = dx(pair) - dx(reference), its std, and the floor: each pixel's floors in quadrature, rms over
    the pixels; units, long names and the pairs named."""
    (ax, ay, bx, by) = 1e-3 * rng.standard_normal((4, 6, 8))
    bx[2, 3] = np.nan
    reference, other = offsets_product(ax, ay, 3e-4), offsets_product(bx, by, 4e-4)
    ds = difference_dataset(reference, other, reference_pair="P14", pair="P24")
    np.testing.assert_array_equal(ds["ddx"].values, bx - ax)
    np.testing.assert_array_equal(ds["ddy"].values, by - ay)
    assert float(ds["ddx_std"]) == np.nanstd(bx - ax) and float(ds["ddy_std"]) == np.std(by - ay)
    assert float(ds["ddx_photon_noise_floor"]) == pytest.approx(5e-4, rel=1e-12)  # hypot(3, 4) e-4
    assert float(ds["ddy_photon_noise_floor"]) == pytest.approx(1e-3, rel=1e-12)
    assert ds.attrs == {"reference_pair": "P14", "pair": "P24"}
    assert ds["ddx"].attrs["long_name"] == "dx(P24) - dx(P14)"
    assert all(ds[name].attrs["units"] == "pixel" for name in ds.data_vars)
    np.testing.assert_array_equal(ds["row"], reference["row"])


def test_with_unobservable_modes_the_difference_is_orthogonal_to_both_pairs(rng):
    """Spherical waves: each pair's modes (and the affine part) taken out of the difference."""
    shape = (6, 8)
    rows, cols = np.indices(shape)
    mode_a = np.stack([np.sin(cols / 2.0)]), np.stack([np.cos(rows / 3.0)])
    mode_b = np.stack([np.cos(cols * rows / 7.0)]), np.stack([np.zeros(shape)])
    ax, ay = 1e-3 * rng.standard_normal((2, *shape))
    noise_x, noise_y = 1e-4 * rng.standard_normal((2, *shape))
    bx = ax + noise_x + 2e-3 * mode_a[0][0] - 1e-3 * mode_b[0][0] + 5e-4 + 1e-5 * cols
    by = ay + noise_y + 2e-3 * mode_a[1][0] - 1e-3 * mode_b[1][0]
    ds = difference_dataset(offsets_product(ax, ay, 1e-4, mode_a), offsets_product(bx, by, 1e-4, mode_b),
                            reference_pair="P14", pair="P24")
    difference = np.concatenate([ds["ddx"].values.ravel(), ds["ddy"].values.ravel()])
    for mode_dx, mode_dy in (mode_a, mode_b):
        assert abs(difference @ np.concatenate([mode_dx[0].ravel(), mode_dy[0].ravel()])) < 1e-15
    assert abs(np.sum(ds["ddx"].values)) < 1e-15 and abs(np.sum(ds["ddy"].values)) < 1e-15
    # what is left is the noise, minus its own projection on the modes and the affine part
    assert np.std(difference) < np.std(np.concatenate([noise_x.ravel(), noise_y.ravel()]))
