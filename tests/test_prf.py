"""PRF width maps from the fringe contrast at two periods per direction, against the simulator's truth."""

import numpy as np
import pytest

from dice_core import fringe_fit, fringes, prf, simulation
from dice_core.detector import PixelResponse
from dice_core.io import FrameStream, read_product
from dice_core.manifest import load_manifest

SMALL = {"shape": [40, 44], "science_rows": [2, 39], "science_cols": [3, 43]}
STARS = {"pattern_centre": [23.0, 20.0], "pattern_side": 16.0}
DEFAULT_GEOMETRY = {  # the default preset's spherical-wave bench
    "spherical": True,
    "baselines": {"H1H4": {"period": 2.4, "angle_deg": 2.0, "midpoint": [0.012, 0.006]},
                  "V1V4": {"period": 2.4, "angle_deg": 93.0, "midpoint": [-0.004, 0.008]},
                  "H2H4": {"period": 4.0, "angle_deg": -3.0, "midpoint": [0.016, -0.009]},
                  "V2V4": {"period": 4.0, "angle_deg": 88.5, "midpoint": [-0.011, -0.010]}}}


def simulate(path, *, detector=None, metrology=None, frames=3000, stars=STARS):
    cfg = simulation.SimulationConfig.from_dict({
        "name": "prf-test", "frames_per_file": 100000, "detector": {**SMALL, **(detector or {})},
        "dark": {"frames": 2}, "flats": {"frames": 2}, "metrology": {"frames": frames, **(metrology or {})},
        "stars": {"positions": 1, "frames": 1, **stars}})
    manifest = load_manifest(simulation.simulate_dataset(cfg, path))
    return manifest, read_product(path / "truth.nc")


def metrology_products(manifest, truth):
    """Each baseline's metrology product, fitted with the true sensitivities as the flat."""
    products = {}
    for name, acquisition in manifest.baselines.items():
        solution = fringe_fit.fit_baseline(FrameStream(acquisition, manifest.detector), truth["bias"].values,
                                           detector=manifest.detector, flat=truth["sensitivity"].values,
                                           read_noise=truth["read_noise"].values, label=name)
        fibers = (f"{name}a", f"{name}b") if solution.two_source is not None else None
        products[name] = fringes.solution_dataset(solution, manifest.detector, fibers=fibers)
    return products


def against_truth(maps, truth, axis):
    """The maps of one axis against the truth, the smooth part of both (the visibility's, which the contrast
    cannot see) and their means taken out, over the mapped pixels:

    - ``scale``: the least-squares factor of the map's deviations on the truth's, and ``scale_sigmas``, its
      distance from 1 in the stated error of the deviations' scale (the kernel shape's);
    - ``photon``: rms of (map - scale x truth) / photon_error_width: the photon noise, the scale fitted;
    - ``pixel``: rms of (map - truth) / error_width_pixel: what the errors of the pixel-scale part cover;
    - ``mean``: (mean width - the truth's mean) / error_mean_width;
    - ``n``: the pixels.
    """
    width = getattr(maps, f"width_{axis}")
    ok = np.isfinite(width)
    rows, cols = np.nonzero(ok)
    mapped = prf.pixel_scale(width[ok], cols, rows, degree=maps.smooth_degree)
    true = prf.pixel_scale(truth[f"width_{axis}"].values[ok], cols, rows, degree=maps.smooth_degree)
    scale = float(mapped @ true / (true @ true))
    photon, pixel = (getattr(maps, f"{name}_{axis}")[ok] for name in ("photon_error_width", "error_width_pixel"))
    return {"scale": scale, "scale_sigmas": (scale - 1) / maps.error_scale[axis] if maps.error_scale[axis] else np.inf,
            "photon": float(np.sqrt(np.mean(((mapped - scale * true) / photon) ** 2))),
            "pixel": float(np.sqrt(np.mean(((mapped - true) / pixel) ** 2))),
            "mean": (maps.mean_width[axis] - float(truth[f"width_{axis}"].values[ok].mean()))
            / maps.error_mean_width[axis] if maps.error_mean_width[axis] else np.inf, "n": int(ok.sum())}


def assert_true_to_the_widths(maps, truth, axis):
    """Each part of the maps within its stated error of the truth (:func:`against_truth`): the scale of the
    deviations and the mean, each one number shared by every pixel, within 3 of their errors; what is left
    of each pixel, within 0.8-1.2 of its photon error. (The total over error_width_pixel is not a test: its
    shape part is one draw for the whole map, so its rms over pixels is that draw's size in its sigma, 1.8
    in one of the four draws of the default bench, docs/centroids.md.)"""
    found = against_truth(maps, truth, axis)
    assert abs(found["scale_sigmas"]) < 3, found
    assert 0.8 < found["photon"] < 1.2, found
    assert abs(found["mean"]) < 3, found
    return found


def test_log_transfer_slope_is_minus_half_k_squared_for_a_gaussian_and_larger_for_the_flat_top():
    k = 2 * np.pi / 2.4
    gaussian = prf.PrfShape(order=2.0, half_width=2.0, sigma=0.25)  # truncated at 8 sigma
    assert prf.log_transfer_slope(k, gaussian) == pytest.approx(-k**2 / 2, rel=1e-6)
    default = prf.PrfShape()
    assert default.width == pytest.approx(0.206, abs=1e-3)
    slope = prf.log_transfer_slope(k, default)
    assert -1.1 * k**2 / 2 < slope < -1.02 * k**2 / 2  # the kernel's fourth moment: 5% more at 2.4 pixels
    # against the detector model's own transfer function: a pixel 1% wider
    ones = np.ones((1, 1))
    wide, mean = (PixelResponse(ones, 0 * ones, 0 * ones, s * ones, 0.3 * ones, 4.0, 0.5) for s in (0.303, 0.3))
    drop = np.log(abs(wide.fringe_response(k, 0.0)[0, 0]) / abs(mean.fringe_response(k, 0.0)[0, 0]))
    assert drop == pytest.approx(slope * (wide.width_x()[0, 0] ** 2 - mean.width_x()[0, 0] ** 2), rel=2e-3)


def test_pixel_scale_removes_the_polynomial_and_keeps_what_is_orthogonal_to_it(rng):
    y, x = np.mgrid[0:30, 0:32].reshape(2, -1).astype(float)
    white = rng.standard_normal(x.size)
    smooth = 1 + 0.01 * x - 3e-4 * x * y + 1e-5 * y**3
    part = prf.pixel_scale(smooth + white, x, y, degree=3)
    assert np.allclose(part, prf.pixel_scale(white, x, y, degree=3))
    assert np.allclose(prf.pixel_scale(part, x, y, degree=3), part)


@pytest.fixture(scope="module")
def symmetric(tmp_path_factory):
    """A 40x44 detector with the default 1% spread of PRF widths, 3000 frames per baseline (4 baselines)."""
    manifest, truth = simulate(tmp_path_factory.mktemp("prf"))
    return manifest, truth, metrology_products(manifest, truth)


@pytest.mark.parametrize("axis", ["x", "y"])
def test_width_maps_agree_with_truth_within_their_errors(symmetric, axis):
    manifest, truth, products = symmetric
    maps = prf.width_maps(products, gain=manifest.detector.gain, read_noise=truth["read_noise"].values,
                          science=manifest.detector.science_mask())
    assert assert_true_to_the_widths(maps, truth, axis)["n"] > 1000
    spread = float(np.std(truth[f"width_{axis}"].values))
    # the pixel-scale errors far below the 1% spread; the mean's error (the kernel's shape) much larger
    assert np.sqrt(np.nanmean(getattr(maps, f"error_width_pixel_{axis}") ** 2)) < 0.1 * spread
    assert 0.7 < maps.chi2 < 1.3  # the two periods agree


def test_width_maps_are_true_on_prfs_of_another_shape(tmp_path):
    """Issue 27, held out: PRFs the presets never use, truncated hyper-Gaussians of order 3 and sigma 0.40
    (width 0.256 pixel, where the presets' kernel is 0.206), asymmetric (slopes of rms 0.05 per pixel), a
    1.5% spread; the family of kernels left at its default. Before the fix (the maps built on the assumed
    kernel) their pixel-to-pixel variations were 1.31-1.32x the truth's, 4.2-4.3x their errors, and their
    mean 0.206 against 0.256. Measured since: the variations 0.98-0.99x (the scale's stated error 1.9-2.3%),
    the mean 0.258-0.261 +- 0.004-0.005, the photon part 1.04x its error, the pixel-scale part 0.99-1.06x
    (7 s on 2 shared cores)."""
    manifest, truth = simulate(tmp_path, detector={"prf_order": 3.0, "prf_sigma": 0.40, "prf_slope_rms": 0.05,
                                                   "prf_width_spread": 0.015})
    maps = prf.width_maps(metrology_products(manifest, truth), gain=manifest.detector.gain,
                          read_noise=truth["read_noise"].values, science=manifest.detector.science_mask())
    for axis in "xy":
        width, error = getattr(maps, f"width_{axis}"), getattr(maps, f"error_width_{axis}")
        ok = np.isfinite(width)
        rows, cols = np.nonzero(ok)
        true = truth[f"width_{axis}"].values[ok]
        mapped, true_part = (prf.pixel_scale(v, cols, rows, degree=maps.smooth_degree) for v in (width[ok], true))
        assert 0.93 < np.std(mapped) / np.std(true_part) < 1.07, axis  # the pixel-to-pixel variations
        assert np.sqrt(np.mean(((mapped - true_part) / error[ok]) ** 2)) < 1.2, axis  # the errors cover them
        assert abs(width[ok].mean() - true.mean()) < 3 * np.sqrt(np.mean(error[ok] ** 2)), axis  # and the mean
        assert_true_to_the_widths(maps, truth, axis)


def test_one_period_per_direction_gives_the_widths_too_but_noisier(symmetric):
    manifest, truth, products = symmetric
    kwargs = dict(gain=manifest.detector.gain, read_noise=truth["read_noise"].values, science=manifest.detector.science_mask())
    both = prf.width_maps(products, **kwargs)
    short = prf.width_maps({k: products[k] for k in ("H1H4", "V1V4")}, **kwargs)
    assert np.isnan(short.chi2)
    # the variance's photon error, 2 w sigma_w (a width's depends on the kernels the data allow)
    variance_error = [np.nanmean(m.photon_error_width_x * m.width_x) for m in (short, both)]
    assert variance_error[0] > 1.05 * variance_error[1]
    # one period says nothing of the shape: the family's whole spread is in the errors
    assert short.error_mean_width["x"] > 2 * both.error_mean_width["x"]
    assert np.nanmean(short.error_width_pixel_x) > 1.5 * np.nanmean(both.error_width_pixel_x)
    assert_true_to_the_widths(short, truth, "x")


def test_a_missing_direction_is_left_nan_and_no_baseline_is_an_error(symmetric):
    manifest, truth, products = symmetric
    maps = prf.width_maps({k: products[k] for k in ("H1H4", "H2H4")}, gain=manifest.detector.gain)
    assert np.all(np.isnan(maps.width_y)) and np.isfinite(maps.width_x).sum() > 1000
    with pytest.raises(ValueError, match="at least one baseline"):
        prf.width_maps({}, gain=10.0)


def test_the_product_holds_the_contract_variables_with_units(symmetric):
    manifest, truth, products = symmetric
    ds = prf.prf_dataset(prf.width_maps(products, gain=manifest.detector.gain, science=manifest.detector.science_mask()))
    for name in ("width_x", "width_y", "error_width_x", "error_width_y", "error_width_pixel_x",
                 "error_width_pixel_y", "variance_deviation_x", "variance_deviation_y"):
        assert ds[name].dims == ("row", "col") and ds[name].attrs["units"] in ("pixel", "pixel2")
        assert np.all(np.isnan(ds[name].values[0]))  # outside the science area
    assert all("units" in ds[v].attrs for v in ds.data_vars)
    for axis in "xy":  # the width is the mean plus the deviation, the variance's pixel-scale part
        assert float(ds[f"kernel_posterior_{axis}"].sum()) == pytest.approx(1.0)
        assert float(ds[f"mean_width_{axis}"]) == pytest.approx(float(ds[f"kernel_posterior_{axis}"]
                                                                      @ ds["kernel_width"]), rel=1e-12)
        variance = ds[f"width_{axis}"] ** 2 - ds[f"mean_width_{axis}"] ** 2
        np.testing.assert_allclose(variance.values, ds[f"variance_deviation_{axis}"].values, rtol=0, atol=2e-5)


def test_an_asymmetric_prf_changes_the_widths_only_at_second_order_in_its_slope(tmp_path):
    """Slopes of rms 0.05 per pixel move the fringe phase by about 2e-3 pixel (docs/metrology.md) but the
    contrast's modulus only by s^2 k^2 w^4 / 2: the widths stay within their errors."""
    manifest, truth = simulate(tmp_path, detector={"prf_slope_rms": 0.05})
    maps = prf.width_maps(metrology_products(manifest, truth), gain=manifest.detector.gain,
                          read_noise=truth["read_noise"].values, science=manifest.detector.science_mask())
    for axis in "xy":
        assert_true_to_the_widths(maps, truth, axis)


@pytest.mark.slow
def test_default_detector_and_bench_width_maps_within_their_errors(tmp_path):
    """The default preset's detector (80x84, 1% spread) and spherical-wave bench, 4000 frames per baseline."""
    cfg_detector = {"shape": [80, 84], "science_rows": [2, 79], "science_cols": [10, 83]}
    manifest, truth = simulate(tmp_path, detector=cfg_detector, metrology=DEFAULT_GEOMETRY, frames=4000, stars={})
    maps = prf.width_maps(metrology_products(manifest, truth), gain=manifest.detector.gain,
                          read_noise=truth["read_noise"].values, science=manifest.detector.science_mask())
    for axis in "xy":
        assert assert_true_to_the_widths(maps, truth, axis)["n"] > 5000
