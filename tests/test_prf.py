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


def error_over_sigma(maps, truth, axis):
    """rms over the mapped pixels of (width - truth) / error, the truth's smooth part taken as the maps'."""
    width, error = getattr(maps, f"width_{axis}"), getattr(maps, f"error_width_{axis}")
    ok = np.isfinite(width)
    rows, cols = np.nonzero(ok)
    true = np.sqrt(maps.shape.width**2 + prf.pixel_scale(truth[f"width_{axis}"].values[ok] ** 2, cols, rows,
                                                         degree=maps.smooth_degree))
    return float(np.sqrt(np.mean(((width[ok] - true) / error[ok]) ** 2))), ok.sum()


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
    ratio, n = error_over_sigma(maps, truth, axis)
    assert n > 1000
    assert 0.8 < ratio < 1.2, ratio  # measured 0.95-1.05
    spread = float(np.std(truth[f"width_{axis}"].values))
    assert np.sqrt(np.nanmean(getattr(maps, f"error_width_{axis}") ** 2)) < 0.1 * spread  # far below the 1% spread
    assert 0.7 < maps.chi2 < 1.3  # the two periods agree


def test_one_period_per_direction_gives_the_widths_too_but_noisier(symmetric):
    manifest, truth, products = symmetric
    kwargs = dict(gain=manifest.detector.gain, read_noise=truth["read_noise"].values, science=manifest.detector.science_mask())
    both = prf.width_maps(products, **kwargs)
    short = prf.width_maps({k: products[k] for k in ("H1H4", "V1V4")}, **kwargs)
    assert np.isnan(short.chi2)
    assert np.nanmean(short.error_width_x) > 1.05 * np.nanmean(both.error_width_x)
    ratio, _ = error_over_sigma(short, truth, "x")
    assert ratio < 1.3


def test_a_missing_direction_is_left_nan_and_no_baseline_is_an_error(symmetric):
    manifest, truth, products = symmetric
    maps = prf.width_maps({k: products[k] for k in ("H1H4", "H2H4")}, gain=manifest.detector.gain)
    assert np.all(np.isnan(maps.width_y)) and np.isfinite(maps.width_x).sum() > 1000
    with pytest.raises(ValueError, match="at least one baseline"):
        prf.width_maps({}, gain=10.0)


def test_the_product_holds_the_contract_variables_with_units(symmetric):
    manifest, truth, products = symmetric
    ds = prf.prf_dataset(prf.width_maps(products, gain=manifest.detector.gain, science=manifest.detector.science_mask()))
    for name in ("width_x", "width_y", "error_width_x", "error_width_y"):
        assert ds[name].dims == ("row", "col") and ds[name].attrs["units"] == "pixel"
        assert np.all(np.isnan(ds[name].values[0]))  # outside the science area
    assert all("units" in ds[v].attrs for v in ds.data_vars)


def test_an_asymmetric_prf_changes_the_widths_only_at_second_order_in_its_slope(tmp_path):
    """Slopes of rms 0.05 per pixel move the fringe phase by about 2e-3 pixel (docs/metrology.md) but the
    contrast's modulus only by s^2 k^2 w^4 / 2: the widths stay within their errors."""
    manifest, truth = simulate(tmp_path, detector={"prf_slope_rms": 0.05})
    maps = prf.width_maps(metrology_products(manifest, truth), gain=manifest.detector.gain,
                          read_noise=truth["read_noise"].values, science=manifest.detector.science_mask())
    for axis in "xy":
        ratio, _ = error_over_sigma(maps, truth, axis)
        assert ratio < 1.2, (axis, ratio)  # 1.02 on 80x84 at 4000 frames


@pytest.mark.slow
def test_default_detector_and_bench_width_maps_within_their_errors(tmp_path):
    """The default preset's detector (80x84, 1% spread) and spherical-wave bench, 4000 frames per baseline."""
    cfg_detector = {"shape": [80, 84], "science_rows": [2, 79], "science_cols": [10, 83]}
    manifest, truth = simulate(tmp_path, detector=cfg_detector, metrology=DEFAULT_GEOMETRY, frames=4000, stars={})
    maps = prf.width_maps(metrology_products(manifest, truth), gain=manifest.detector.gain,
                          read_noise=truth["read_noise"].values, science=manifest.detector.science_mask())
    for axis in "xy":
        ratio, n = error_over_sigma(maps, truth, axis)
        assert n > 5000 and ratio < 1.2, (axis, ratio)
