"""Chromatic pixels: silicon's absorption, the depth kernels, the spectra, the simulator's response model and
the reduction's model across wavelength (dice_core.chromatic)."""

import numpy as np
import pytest

from dice_core import chromatic
from dice_core.detector import PixelResponse


def test_the_absorption_length_is_silicon_s():
    """The issue's numbers: about 0.1 um at 400 nm, 3 um at 633 nm, 10 um at 800 nm (Schinke et al. 2015)."""
    lengths = chromatic.absorption_length(np.array([400e-9, 633e-9, 800e-9]))
    np.testing.assert_allclose(lengths, [0.098e-6, 3.19e-6, 12.1e-6], rtol=0.01)
    assert np.all(np.diff(chromatic.absorption_length(np.linspace(380e-9, 1000e-9, 200))) > 0)
    with pytest.raises(ValueError, match="outside the silicon absorption table"):
        chromatic.absorption_length(1.1e-6)


def test_the_depth_kernels_have_their_limits():
    # thick silicon: light absorbed near the entrance travels the whole thickness, the surface layer sees it all
    drift, surface = chromatic.depth_kernels(400e-9, thickness=1e-3, surface_depth=1e-6)
    length = chromatic.absorption_length(400e-9)
    assert drift == pytest.approx(1 - length / 1e-3, rel=1e-9)
    assert surface == pytest.approx(1e-6 / (1e-6 + length), rel=1e-9)
    # silicon much thinner than the absorption length: absorbed evenly, half the thickness on average
    drift, surface = chromatic.depth_kernels(1000e-9, thickness=1e-6, surface_depth=1e-6)
    assert drift == pytest.approx(0.5, abs=0.01)
    with pytest.raises(ValueError, match="must be > 0"):
        chromatic.depth_kernels(600e-9, thickness=0.0, surface_depth=1e-7)


def test_the_named_spectra():
    wavelength, flat = chromatic.named_spectrum("flat")
    assert wavelength[0] == 400e-9 and wavelength[-1] == 800e-9 and len(wavelength) == 21
    assert repr(wavelength[2]) == "4.4e-07" or float(wavelength[2]) == 4.4e-07  # spelt as written
    np.testing.assert_allclose(flat, 1.0)
    _, warm = chromatic.named_spectrum("warm")
    _, cool = chromatic.named_spectrum("cool")
    assert np.all(np.diff(warm) > 0) and np.all(np.diff(cool) < 0)  # a red-heavy and a blue-heavy black body
    assert warm.mean() == pytest.approx(1.0) and cool.mean() == pytest.approx(1.0)
    with pytest.raises(ValueError, match="unknown spectrum 'blue'"):
        chromatic.named_spectrum("blue")


def test_quadrature_weights_integrate_piecewise_linear_functions_exactly():
    grid = np.array([400.0, 420.0, 450.0, 500.0, 633.0, 700.0, 800.0]) * 1e-9
    samples, density = np.array([410.0, 500.0, 700.0]) * 1e-9, np.array([1.0, 3.0, 2.0])
    weights = chromatic.quadrature_weights(grid, (samples, density))
    assert weights.sum() == pytest.approx(1.0)

    def f(w):
        return 2.0 + w * 1e6  # linear: its integral against the density is exact whatever the grid

    fine = np.linspace(410e-9, 700e-9, 200001)
    d = chromatic.spectrum_density(fine, (samples, density))
    expected = np.trapezoid(f(fine) * d, fine) / np.trapezoid(d, fine)
    # exact where the grid holds the spectrum's samples (its kinks), as the simulator's and the model's grids do
    on_samples = np.unique(np.concatenate([grid, samples]))
    assert chromatic.quadrature_weights(on_samples, (samples, density)) @ f(on_samples) == pytest.approx(expected,
                                                                                                     rel=1e-6)
    with pytest.raises(ValueError, match="no light"):
        chromatic.quadrature_weights(grid, (np.array([900e-9, 950e-9]), np.ones(2)))


def base_response(rng, shape=(60, 64)):
    return PixelResponse(1 + 2e-3 * rng.standard_normal(shape), 1e-3 * rng.standard_normal(shape),
                         1e-3 * rng.standard_normal(shape), 0.3 * (1 + 0.01 * rng.standard_normal(shape)),
                         0.3 * (1 + 0.01 * rng.standard_normal(shape)))


def unit_fields(rng, shape=(60, 64)):
    return {name: list(rng.standard_normal((2, *shape))) for name in ("sensitivity", "dx", "dy", "sigma_x",
                                                                       "sigma_y")}


OPTIONS = dict(reference=633e-9, sensitivity_rms=2e-3, offset_rms=1e-3, width_rms=0.01, width_trend=0.05,
               thickness=16e-6, surface_depth=0.3e-6, surface_share=0.5)


def test_the_chromatic_response_is_the_base_at_the_reference_and_changes_by_its_rms_at_400_nm(rng):
    base, fields = base_response(rng), unit_fields(rng)
    mask = np.ones(base.shape, bool)
    out = chromatic.chromatic_response(base, [400e-9, 633e-9, 800e-9], fields=fields, amplitude=3.0, mask=mask, **OPTIONS)
    for name, value in (("sensitivity", base.sensitivity), ("dx", base.dx), ("sigma_y", base.sigma_y)):
        assert np.array_equal(out[name][1], value), name  # bit for bit at the reference
    # the change to 400 nm: amplitude x rms (the two unit fields' rms, about 1 over 3840 pixels)
    assert np.std(out["dx"][0] - base.dx) == pytest.approx(3.0 * 1e-3, rel=0.05)
    relative = out["sensitivity"][0] / base.sensitivity - 1
    assert np.std(relative) == pytest.approx(3.0 * 2e-3, rel=0.05)
    assert out["sensitivity"][0].mean() == pytest.approx(base.sensitivity.mean(), rel=1e-12)  # the mean kept
    # the PRF scale: the spread's change and the trend, wider in the blue
    assert np.mean(out["sigma_x"][0] / base.sigma_x) == pytest.approx(1 + 3.0 * 0.05, rel=2e-3)
    # the red side changes the other way (light absorbed nearer the wells), the surface layer's hardly at all
    drift, surface = chromatic.change_coefficients(800e-9, reference=633e-9, thickness=16e-6, surface_depth=0.3e-6,
                                                   surface_share=0.5)
    assert drift < -0.5 and -0.1 < surface < 0
    still = chromatic.chromatic_response(base, [400e-9], fields={}, amplitude=0.0, mask=mask, **OPTIONS)
    assert np.array_equal(still["dx"][0], base.dx)  # amplitude 0: achromatic, no field needed
    with pytest.raises(ValueError, match="the one the amplitudes are stated at"):
        chromatic.change_coefficients(600e-9, reference=400e-9, thickness=16e-6, surface_depth=0.3e-6,
                                      surface_share=0.5)
