"""The PRF model against brute-force integration on a fine grid."""

import numpy as np
import pytest

from dice_core.detector import PixelResponse, hyper_gaussian_std


def detector(rng, shape=(5, 6), order=4.0, half_width=0.5):
    return PixelResponse(1 + 0.01 * rng.standard_normal(shape), 1e-2 * rng.standard_normal(shape),
                         1e-2 * rng.standard_normal(shape), 0.3 * (1 + 0.05 * rng.standard_normal(shape)),
                         0.3 * (1 + 0.05 * rng.standard_normal(shape)), order, half_width)


def brute_force(prf, r, c, function, n=2001):
    """Integral of PRF(x, y) * function(x, y) for pixel (r, c) on an n x n midpoint grid."""
    a = prf.half_width
    u = (np.arange(n) + 0.5) / n * 2 * a - a
    gx = np.exp(-np.abs(u) ** prf.order / (2 * prf.sigma_x[r, c] ** prf.order))
    gy = np.exp(-np.abs(u) ** prf.order / (2 * prf.sigma_y[r, c] ** prf.order))
    x0, y0 = c + prf.dx[r, c], r + prf.dy[r, c]
    weights = np.outer(gy, gx) / (gy.sum() * gx.sum())
    yy, xx = np.meshgrid(y0 + u, x0 + u, indexing="ij")
    return prf.sensitivity[r, c] * np.sum(weights * function(xx, yy))


def test_width_is_the_prf_standard_deviation():
    a = 0.5
    u = (np.arange(200001) + 0.5) / 200001 * 2 * a - a
    g = np.exp(-np.abs(u) ** 4 / (2 * 0.3**4))
    assert hyper_gaussian_std(0.3, order=4, half_width=a) == pytest.approx(np.sqrt((g * u**2).sum() / g.sum()), rel=1e-8)
    # order 2 without truncation is a Gaussian of standard deviation sigma
    assert hyper_gaussian_std(0.3, order=2, half_width=3.0) == pytest.approx(0.3, rel=1e-6)


@pytest.mark.parametrize("kx, ky", [(2 * np.pi / 2.4, 0.1), (0.05, 2 * np.pi / 4.0), (1.9, -1.2)])
def test_fringe_response_is_the_prf_integral_of_the_fringe(rng, kx, ky):
    prf = detector(rng)
    response = prf.fringe_response(kx, ky)
    for r, c in [(0, 0), (2, 3), (4, 5)]:
        expected = brute_force(prf, r, c, lambda x, y: np.exp(1j * (kx * x + ky * y)))
        assert response[r, c] == pytest.approx(expected, rel=1e-6, abs=1e-9)


def test_fringe_phase_is_exactly_k_dot_true_centre(rng):
    prf = detector(rng)
    kx, ky = 2.0, 0.7
    x0, y0 = prf.centres()
    phase = np.angle(prf.fringe_response(kx, ky) * np.exp(-1j * (kx * x0 + ky * y0)))
    np.testing.assert_allclose(phase, 0.0, atol=1e-13)


def test_gaussian_response_is_the_prf_integral_of_the_psf(rng):
    prf = detector(rng)
    xs, ys, s = 2.3, 1.7, 1.3
    psf = lambda x, y: np.exp(-0.5 * ((x - xs) ** 2 + (y - ys) ** 2) / s**2) / (2 * np.pi * s**2)
    response = prf.gaussian_response(xs, ys, s)
    for r, c in [(1, 2), (2, 2), (4, 0)]:
        assert response[r, c] == pytest.approx(brute_force(prf, r, c, psf), rel=1e-6)
    window = prf.gaussian_response(xs, ys, s, rows=slice(1, 3), cols=slice(2, 4))
    np.testing.assert_array_equal(window, response[1:3, 2:4])


def test_gaussian_response_conserves_flux_on_a_uniform_detector():
    shape = (40, 40)
    prf = PixelResponse(np.ones(shape), np.zeros(shape), np.zeros(shape), np.full(shape, 0.3),
                        np.full(shape, 0.3), 4.0, 0.5)
    assert prf.gaussian_response(19.3, 20.6, 1.3).sum() == pytest.approx(1.0, rel=1e-4)

