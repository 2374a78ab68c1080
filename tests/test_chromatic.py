"""Chromatic pixels: silicon's absorption, the depth kernels, the spectra, the simulator's response model and
the reduction's model across wavelength (dice_core.chromatic)."""

import numpy as np
import pytest

from dice_core import chromatic, io
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


# ------------------------------------------------------------------ the reduction's model across wavelength

def test_the_model_reproduces_quadratics_in_the_depth_coordinate_and_fits_more_wavelengths():
    calibration = np.array([450e-9, 633e-9, 800e-9])
    grid = np.linspace(400e-9, 850e-9, 46)
    x, xc = chromatic.depth_coordinate(grid), chromatic.depth_coordinate(calibration)
    weights = chromatic.model_weights(calibration, grid)
    np.testing.assert_allclose(weights.sum(axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(weights @ (1 + 2 * xc - 0.3 * xc**2), 1 + 2 * x - 0.3 * x**2, atol=1e-10)
    # two wavelengths: a straight line; one: a constant
    np.testing.assert_allclose(chromatic.model_weights(calibration[:2], grid) @ (3 - xc[:2]), 3 - x, atol=1e-10)
    np.testing.assert_allclose(chromatic.model_weights([633e-9], grid), 1.0)
    # five: a least-squares quadratic, which averages noise (at the calibration wavelengths, weights below 1)
    five = np.array([420e-9, 500e-9, 633e-9, 700e-9, 800e-9])
    at_five = chromatic.model_weights(five, five)
    assert np.all(np.diag(at_five) < 1) and np.allclose(at_five @ chromatic.depth_coordinate(five) ** 2,
                                                        chromatic.depth_coordinate(five) ** 2)
    with pytest.raises(ValueError, match="distinct"):
        chromatic.model_weights([633e-9, 633e-9], grid)
    with pytest.raises(ValueError, match="degree 2 needs 3"):
        chromatic.model_weights(calibration[:2], grid, degree=2)


@pytest.fixture(scope="module")
def chromatic_truth():
    """The default detector made chromatic (amplitude 5), with its response at 8 candidate wavelengths."""
    from dice_core import simulation

    cfg = simulation.SimulationConfig.from_dict({
        "chromatic": {"amplitude": 5.0}, "stars": {"spectrum": "flat"},
        "flats": {"wavelengths": [420e-9, 450e-9, 500e-9, 550e-9, 633e-9, 700e-9, 800e-9]}})
    truth = simulation.make_truth(cfg)
    mask = np.zeros(cfg.detector.shape, bool)
    mask[slice(*cfg.detector.science_rows), slice(*cfg.detector.science_cols)] = True
    return truth, mask


def seen_by(truth, spectrum):
    """What a spectrum sees of each pixel, from the truth's own grid (the simulator's sum): (s, dx, dy)."""
    from dice_core import simulation

    grid = truth["wavelength"].values
    a = chromatic.quadrature_weights(grid, spectrum)
    s = np.tensordot(a, truth["sensitivity_wavelength"].values, axes=1)
    return (s / s.mean(), *(np.tensordot(a, truth["sensitivity_wavelength"].values * truth[f"{n}_wavelength"].values,
                                         axes=1) / s for n in ("dx", "dy")))


#: The effective maps' error with 450, 633 and 800 nm, over the 633 nm maps' error: measured 0.042, 0.147 and 0.024
#: (the warm stars' light is mostly beyond 633 nm, where the drift kernel bends most); with 450 and 633 nm only,
#: 0.45, 0.80 and 0.15; with five wavelengths (420-800 nm) 0.004, 0.081, 0.020.
THREE_WAVELENGTHS_BOUND = {"flat": 0.06, "warm": 0.2, "cool": 0.04}


@pytest.mark.parametrize("name", ["flat", "warm", "cool"])
def test_three_wavelengths_give_what_a_broadband_star_sees_where_633_nm_alone_does_not(chromatic_truth, name):
    """Against the truth: the effective sensitivity and offsets of 450, 633 and 800 nm's maps through the model,
    against the error the 633 nm maps alone leave (THREE_WAVELENGTHS_BOUND); two wavelengths, a blue one and 633
    nm, do at least twice as badly (extrapolating to the red)."""
    truth, mask = chromatic_truth
    spectrum = chromatic.named_spectrum(name)
    seen = dict(zip(("sensitivity", "dx", "dy"), seen_by(truth, spectrum)))

    def rms(values):
        return float(np.sqrt(np.mean(values[mask] ** 2)))

    alone = {n: rms(seen[n] - truth[n].values) for n in seen}
    assert alone["dx"] > 3e-4 and alone["sensitivity"] > 1e-3  # what a 633 nm calibration misses, for these stars
    ratios = {}
    for calibration in ((450e-9, 633e-9, 800e-9), (450e-9, 633e-9)):
        at = truth.sel(wavelength=list(calibration))
        effective = chromatic.effective_response(
            calibration, {"dx": at["dx_wavelength"].values, "dy": at["dy_wavelength"].values}, spectrum=spectrum,
            sensitivity=at["sensitivity_wavelength"].values, sensitivity_wavelengths=calibration)
        ratios[len(calibration)] = {n: rms(getattr(effective, n) - seen[n]) / alone[n] for n in seen}
        assert sum(effective.weights.values()) == pytest.approx(1.0)
    for n in seen:
        assert ratios[3][n] < THREE_WAVELENGTHS_BOUND[name], n
        assert ratios[2][n] > 2 * ratios[3][n], n


def product_from_truth(truth, calibration, *, flats=True):
    """calibration/chromatic.nc made of the truth's maps at ``calibration`` (m), as the workflow makes it of
    measured ones; the widths as width maps hold them (their mean is the assumed kernel's, here the truth's)."""
    from types import SimpleNamespace

    import xarray as xr

    at = {w: truth.sel(wavelength=w) for w in calibration}
    offsets = {w: xr.Dataset({"dx": at[w]["dx_wavelength"], "dy": at[w]["dy_wavelength"]}) for w in calibration}
    widths = {w: SimpleNamespace(width_x=at[w]["width_x_wavelength"].values, width_y=at[w]["width_y_wavelength"].values)
              for w in calibration}
    sensitivity = {w: at[w]["sensitivity_wavelength"].values for w in calibration} if flats else {}
    return chromatic.chromatic_dataset(calibration, offsets=offsets, widths=widths, sensitivity=sensitivity,
                                       pairs={w: f"P14_{w * 1e9:.0f}" for w in calibration},
                                       flats={w: f"laser_{w * 1e9:.0f}" for w in calibration} if flats else {},
                                       reference=633e-9)


def test_the_star_calibration_from_the_product_is_the_model_s(chromatic_truth, tmp_path):
    truth, mask = chromatic_truth
    calibration = (633e-9, 450e-9, 800e-9)  # the manifest's order: the reference pair's first
    product = product_from_truth(truth, calibration)
    io.write_product(product, tmp_path / "chromatic.nc", title="t")  # a product (every coordinate said what it is)
    assert product["dx"].dims == ("wavelength", "row", "col") and list(product["pair"].values)[0] == "P14_633"
    for name, units in (("dx", "pixel"), ("dy", "pixel"), ("sensitivity", "1"), ("width_x", "pixel")):
        assert product[name].attrs["units"] == units
    assert "ln(silicon absorption length" in product.attrs["model"] and product.attrs["reference_wavelength"] == 633e-9
    spectrum = chromatic.named_spectrum("cool")
    found = chromatic.star_calibration(product, spectrum, white_prnu=truth["sensitivity"].values)
    s_true, dx_true, _ = seen_by(truth, spectrum)
    assert np.sqrt(np.mean((found["dx"] - dx_true)[mask] ** 2)) < 0.06 * np.sqrt(np.mean(
        (truth["dx"].values - dx_true)[mask] ** 2))
    # the widths: the effective variance's change from 633 nm; the cool stars see wider PRFs (the trend)
    assert np.mean(found["variance_x"][mask]) > 0
    # fewer than two laser flats: the white flat stands for the sensitivity
    white = truth["sensitivity"].values * 1.01
    without = chromatic.star_calibration(product_from_truth(truth, calibration, flats=False), spectrum,
                                         white_prnu=white)
    np.testing.assert_allclose(without["prnu"], white / white.mean())
    # the offsets then weighted by a constant: their weighting by the sensitivity's change is second order, the
    # change (1% at 400 nm at amplitude 5) times the offsets' across the band (measured 2e-5 pixel rms)
    assert np.sqrt(np.mean((without["dx"] - found["dx"])[mask] ** 2)) < 4e-5


def test_on_an_achromatic_detector_the_star_calibration_is_flat_and_metrology_s():
    from dice_core import simulation

    cfg = simulation.SimulationConfig.from_dict({"stars": {"spectrum": "warm"},
                                                 "flats": {"wavelengths": [450e-9, 633e-9, 800e-9]}})
    truth = simulation.make_truth(cfg)
    product = product_from_truth(truth, (633e-9, 450e-9, 800e-9))
    found = chromatic.star_calibration(product, chromatic.named_spectrum("warm"), white_prnu=truth["sensitivity"].values)
    np.testing.assert_allclose(found["dx"], truth["dx"].values, rtol=0, atol=1e-15)
    np.testing.assert_allclose(found["prnu"], truth["sensitivity"].values / np.mean(truth["sensitivity"].values),
                               rtol=1e-12)
    assert np.max(np.abs(found["variance_x"])) < 1e-15


@pytest.mark.slow  # 1-2 min: 4000 frames of a baseline simulated, fitted twice (2 shared cores, 2026-12-04)
def test_a_wavelength_s_offsets_reach_their_floor_with_its_own_flat_as_the_gauge_s(tmp_path):
    """A 450 nm baseline of the default detector made chromatic (amplitude 5), 4000 frames: with the 450 nm laser
    flat for its gauge (what the workflow takes where the dataset has one) its projected offsets are at the photon
    floor against the 450 nm truth (measured 1.02); with the white flat, whose sensitivities are not the laser's,
    the gauge ripples them (3.1 times the floor; docs/metrology.md, "A flat that is not the laser's response")."""
    from dice_core import fringe_fit, simulation
    from dice_core.io import FrameStream
    from dice_core.manifest import parse_manifest

    cfg = simulation.SimulationConfig.from_dict({
        "name": "gauge", "frames_per_file": 4000, "metrology": {
            "frames": 4000, "wavelengths": [633e-9, 450e-9], "pairs": {"P14": ["H1H4", "V1V4"]},
            "baselines": {"H1H4": {"period": 2.4, "angle_deg": 2.0}, "V1V4": {"period": 2.4, "angle_deg": 93.0}}},
        "flats": {"wavelengths": [450e-9]}, "stars": {"spectrum": "flat", "positions": 2, "frames": 2},
        "chromatic": {"amplitude": 5.0}})
    truth = simulation.make_truth(cfg)
    manifest = parse_manifest(simulation.dataset_layout(cfg), tmp_path / "dataset.yaml")
    for relpath in simulation.acquisition_files(cfg, "baseline", name="V1V4_450"):
        simulation.write_file(cfg, truth, relpath=relpath, outdir=tmp_path)
    at = truth.sel(wavelength=450e-9)
    flats = {"white": np.tensordot(truth["flat_spectrum_weight"].values, truth["sensitivity_wavelength"].values,
                                   axes=1), "450 nm": at["sensitivity_wavelength"].values}
    ratios = {}
    for name, flat in flats.items():
        solution = fringe_fit.fit_baseline(FrameStream(manifest.baselines["V1V4_450"], manifest.detector),
                                           truth["bias"].values, detector=manifest.detector, flat=flat,
                                           read_noise=truth["read_noise"].values, label=f"V1V4_450, {name} flat")
        rows, cols = solution.rows, solution.cols
        k = solution.k / np.hypot(*solution.k)
        error = solution.offsets - (k[0] * at["dx_wavelength"].values[rows, cols]
                                    + k[1] * at["dy_wavelength"].values[rows, cols])
        design = np.column_stack([np.ones(rows.size), cols, rows])  # the offsets' affine gauge
        error -= design @ np.linalg.lstsq(design, error, rcond=None)[0]
        ratios[name] = float(np.sqrt(np.mean(error**2) / np.mean(solution.photon_floor**2)))
    assert ratios["450 nm"] < 1.2 < 1.5 < ratios["white"]


def test_three_wavelengths_hold_over_the_thicknesses_and_surface_layers_the_docs_advise_for():
    """docs/centroids.md's advice rests on this: over silicon 10, 16 and 40 um thick and surface layers of 0.1,
    0.3 and 1 um, each depth kernel and spectrum taken alone, the model's error for what a spectrum sees over
    633 nm alone's is at most 0.29 with 450, 633 and 800 nm (measured 0.279), 0.66 with the five wavelengths
    (0.655: they end at 800 nm too, their extra points no help for 40 um), and reaches 5 with 450 and 633 nm."""
    sets = {"three": (450e-9, 633e-9, 800e-9), "five": (420e-9, 500e-9, 633e-9, 700e-9, 800e-9),
            "two": (450e-9, 633e-9)}
    worst = dict.fromkeys(sets, 0.0)
    for key, calibration in sets.items():
        for thickness in (10e-6, 16e-6, 40e-6):
            for surface in (0.1e-6, 0.3e-6, 1e-6):
                kernels_at = np.array(chromatic.depth_kernels(np.array(calibration), thickness=thickness,
                                                              surface_depth=surface))
                alone = np.array(chromatic.depth_kernels(633e-9, thickness=thickness, surface_depth=surface))
                for name in ("flat", "warm", "cool"):
                    spectrum = chromatic.named_spectrum(name)
                    grid = chromatic.spectrum_grid(spectrum[0], calibration=calibration)
                    a = chromatic.quadrature_weights(grid, spectrum)
                    model = a @ chromatic.model_weights(calibration, grid)
                    seen = a @ np.array(chromatic.depth_kernels(grid, thickness=thickness, surface_depth=surface)).T
                    ratio = np.abs(kernels_at @ model - seen) / np.abs(alone - seen)
                    worst[key] = max(worst[key], float(ratio.max()))
    assert worst["three"] < 0.29 and worst["five"] < 0.66 and worst["two"] > 4


def test_a_spectrum_beyond_the_calibration_wavelengths_is_warned_of():
    """Extrapolation, shares whose absolute sum passes 1.5 and a straight line from two wavelengths are said;
    a spectrum inside three wavelengths is not."""
    inside = chromatic.named_spectrum("flat", band=(450e-9, 800e-9))
    grid = chromatic.spectrum_grid(inside[0], calibration=(450e-9, 633e-9, 800e-9))
    shares = dict(zip((450e-9, 633e-9, 800e-9), chromatic.quadrature_weights(grid, inside) @ chromatic.model_weights(
        (450e-9, 633e-9, 800e-9), grid)))
    assert chromatic.extrapolation_warning((450e-9, 633e-9, 800e-9), inside, shares=shares) is None
    red = (np.array([850e-9, 1000e-9]), np.array([1.0, 1.0]))
    said = chromatic.extrapolation_warning((450e-9, 633e-9, 800e-9), red, shares={450e-9: 0.57, 633e-9: -2.54,
                                                                                 800e-9: 2.97})
    assert "850-1000 nm reaches beyond the calibration wavelengths' 450-800 nm" in said and "sum to 6.08" in said
    assert "straight line" in chromatic.extrapolation_warning((450e-9, 633e-9), inside, shares={450e-9: 0.4,
                                                                                                633e-9: 0.6})
