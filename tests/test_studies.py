"""Simulation studies of the paper: its own offset reduction against ours, the sweep points' products."""

import numpy as np
import pytest

from dice_core import error_budget, io, reproduction, studies


def bench(prnu):
    return studies.apply_overrides(studies.OFFSET_BIAS_BENCH, {"detector.prnu_rms": prnu, "metrology.frames": 8000,
                                                               "frames_per_file": 4000})


@pytest.fixture(scope="module")
def bias_points(tmp_path_factory):
    """The offset-bias study at the paper's two PRNU levels, 8000 frames with noise, 3 noiseless patterns."""
    work = tmp_path_factory.mktemp("offset-bias")
    return {prnu: studies.offset_bias(bench(prnu), workdir=work, noiseless_frames=2000, noiseless_draws=3)
            for prnu in (5e-5, 2e-3)}


def test_ours_stays_at_the_photon_floor_at_both_prnu_levels(bias_points, tmp_path):
    for ds in bias_points.values():
        io.write_product(ds, tmp_path / "point.nc", title="an offset-bias point")  # as the sweep's step writes it
        assert float(ds.rms_error_ours) < 1.2 * float(ds.rms_photon_floor)
        assert float(ds.rms_bias_ours) < 1e-8  # noiseless: no bias at all
        # without a flat (the PRNU-free gauge): no help from the truth, no PRNU-dependent bias either
        assert float(ds.rms_error_ours_no_flat) < 1.2 * float(ds.rms_photon_floor)
        assert float(ds.rms_bias_ours_no_flat) < 1e-7


def test_the_papers_method_leaves_a_bias_that_grows_with_the_prnu(bias_points):
    low, high = bias_points[5e-5], bias_points[2e-3]
    assert float(high.rms_bias_paper) > 5 * float(low.rms_bias_paper)
    assert float(high.rms_bias_paper) > 1e4 * float(high.rms_bias_ours)
    assert float(high.rms_bias_paper) > 3e-6  # pixel: well above ours, below the paper's 1e-4
    # each noiseless PRNU pattern has its own bias: a random Fourier component of the pattern
    assert np.ptp(high.draw_bias_paper.values) > 0.1 * float(high.rms_bias_paper)


def test_the_papers_bias_is_a_pattern_at_the_fringe_frequency(bias_points):
    """Most of the paper's noiseless error projects on cos and sin of the pixel phase and twice it."""
    ds = bias_points[2e-3]
    bias = ds.bias_paper.values
    rows, cols = np.nonzero(np.isfinite(bias))
    values = bias[rows, cols]
    period, angle = 2.4, np.radians(2.0)
    phase = 2 * np.pi / period * (np.cos(angle) * cols + np.sin(angle) * rows)
    design = np.column_stack([np.cos(phase), np.sin(phase), np.cos(2 * phase), np.sin(2 * phase)])
    fitted = design @ np.linalg.lstsq(design, values, rcond=None)[0]
    assert np.sqrt(np.mean(fitted**2)) > 0.5 * np.sqrt(np.mean(values**2))


def test_overrides_reach_nested_keys_and_refuse_unknown_sections():
    settings = studies.apply_overrides(studies.OFFSET_BIAS_BENCH, {"detector.prnu_rms": np.float64(5e-5), "seed": 3})
    assert settings["detector"]["prnu_rms"] == 5e-5 and type(settings["detector"]["prnu_rms"]) is float
    assert settings["seed"] == 3 and studies.OFFSET_BIAS_BENCH["detector"]["prnu_rms"] == 2e-3  # a copy
    assert studies.apply_overrides(studies.OFFSET_BIAS_BENCH, {"detector.prnu_rms": "2e-3"})["detector"]["prnu_rms"] == 2e-3
    with pytest.raises(ValueError, match="detector.prnu_rms: 'high' is not a number"):
        studies.apply_overrides(studies.OFFSET_BIAS_BENCH, {"detector.prnu_rms": "high"})
    with pytest.raises(KeyError, match="no section 'detectr'"):
        studies.apply_overrides(studies.OFFSET_BIAS_BENCH, {"detectr.prnu_rms": 1.0})


def test_an_error_propagation_point_round_trips_through_its_product(tmp_path):
    from dice_core.io import read_product, write_product

    ds = studies.run_point("error_propagation", {"source": "offsets", "weighting": "uniform"},
                           bench={"star.psf_sigma": 1.6}, options={"trials": 50, "amplitudes": [1e-3, 1e-2]})
    write_product(ds, tmp_path / "point.nc", title="point")
    back = studies.sweep_from_dataset(read_product(tmp_path / "point.nc"))
    direct = error_budget.sweep("offsets", [1e-3, 1e-2], trials=50, weighting="uniform",
                                star=error_budget.Star(psf_sigma=1.6))
    assert back.source == "offsets" and back.weighting == "uniform" and back.star.psf_sigma == 1.6
    assert back.coefficient == pytest.approx(direct.coefficient, rel=1e-12)
    assert back.prediction.coefficient == pytest.approx(direct.prediction.coefficient, rel=1e-12)
    with pytest.raises(KeyError, match="only star"):
        studies.run_point("error_propagation", {"source": "prnu"}, bench={"detector.gain": 1.0})
    with pytest.raises(ValueError, match="unknown study"):
        studies.run_point("nonsense", {})


def test_the_combined_table_has_one_row_per_source_with_the_unweighted_fit_beside():
    sweeps = [error_budget.sweep(s, [1e-3], trials=40, weighting=w) for s in ("prnu", "read")
              for w in ("pipeline", "uniform")]
    rows = error_budget.combined_table(sweeps)
    assert [r["source"] for r in rows] == ["prnu", "read"]
    assert all(r["weighting"] == "pipeline" for r in rows)
    uniform = error_budget.error_propagation_table([sw for sw in sweeps if sw.weighting == "uniform"])
    assert rows[0]["coefficient_uniform"] == uniform[0]["coefficient"]
    header = error_budget.error_propagation_csv(rows).splitlines()[0].split(",")
    assert header[:5] == ["source", "normalisation", "coefficient", "error", "paper_coefficient"]
    assert "coefficient_uniform" in header


def test_the_procrustes_deflation_of_the_papers_geometry_is_its_1_4():
    factor, error = reproduction.procrustes_deflation(33, trials=1000)
    assert factor == pytest.approx(1.4, abs=0.06) and error < 0.01
    # about sqrt(2SN / (2SN - 5N - 2S + 4)) for S stars and N positions
    assert factor == pytest.approx(np.sqrt(330 / (330 - 165 - 10 + 4)), rel=0.02)


def test_the_comparison_table_follows_the_contract():
    import csv
    import io

    rows = [reproduction.Row("deflation", 1.44, 0.004, "nominal geometry", "a note, with a comma")]
    parsed = list(csv.DictReader(io.StringIO(reproduction.comparison_csv(rows))))
    assert list(parsed[0])[:6] == ["quantity", "section", "paper", "ours", "error", "unit"]
    assert float(parsed[0]["paper"]) == 1.4 and float(parsed[0]["ours"]) == 1.44
    assert parsed[0]["note"] == "a note, with a comma" and parsed[0]["section"] == "Numerical simulations"


def test_offset_bias_rows_take_the_noisy_error_at_5e_5_and_the_bias_at_2e_3(bias_points):
    all_rows = reproduction.offset_bias_rows(bias_points)
    rows = {row.key: row for row in all_rows if row.key}
    assert rows["bias_paper_5e-5"].ours == float(bias_points[5e-5].rms_error_paper)
    assert rows["bias_paper_2e-3"].ours == float(bias_points[2e-3].rms_bias_paper)
    assert rows["bias_paper_2e-3"].error == pytest.approx(np.std(bias_points[2e-3].draw_bias_paper.values, ddof=1))
    # the rms of each map of the figure has its own row (the paper's number where it is one), no quantity twice
    maps = {row.as_dict()["quantity"]: row.ours for row in all_rows}
    assert len(maps) == len(all_rows) == 2 + 2 * len(reproduction.BIAS_MAPS) - 1
    for level, text in ((5e-5, "5e-5"), (2e-3, "2e-3")):
        ds = bias_points[level]
        assert maps[f"offset error rms of ours (true flat), with photon noise, PRNU RSD {text}"] == float(
            ds.rms_error_ours)
        assert maps[f"offset bias rms of the paper's method, noiseless, rms over the PRNU patterns, PRNU RSD {text}"] == float(
            ds.rms_bias_paper)
    assert maps["offset error rms of the paper's method, with photon noise, PRNU RSD 2e-3"] == float(
        bias_points[2e-3].rms_error_paper)


def test_allan_rows_hold_the_measured_value_and_name_its_group_size():
    """Ours as measured at our largest group, the quantity saying how many frames; the paper's 100,000-frame
    scaling only in the note (a scaled value is no measurement)."""
    import xarray as xr

    allan = xr.Dataset({"deviation_mean": ("n_frames", [4e-4, 2e-4]), "deviation_block_mean": ("n_frames", [4e-5, 2e-5]),
                        "photon_limit_pixel": ("n_frames", [4e-4, 2e-4]), "photon_limit_block": ("n_frames", [4e-5, 2e-5]),
                        "slope": ((), -0.5)}, coords={"n_frames": [625, 2500]}, attrs={"baseline": "H1H4"})
    pixel, block = reproduction.allan_rows(allan, dataset="sim")
    assert pixel.ours == 2e-4 and block.ours == 2e-5
    assert pixel.as_dict()["quantity"].endswith("individual pixels (H1H4, 2500 frames per group)")
    assert pixel.dataset == "sim H1H4" and f"{2e-4 * np.sqrt(2500 / 1e5):.2e}" in pixel.note


def test_the_comparison_table_refuses_a_quantity_twice():
    """One row per number of the paper: a second way to get it is its own quantity (a variant)."""
    rows = [reproduction.Row("coefficient_prnu", 0.4), reproduction.Row("coefficient_prnu", 0.28)]
    with pytest.raises(ValueError, match="more than one row"):
        reproduction.comparison_csv(rows)
    rows[1].variant = "unweighted fit"
    text = reproduction.comparison_csv(rows)
    assert "centroid error per unit PRNU RSD (unweighted fit)" in text
    records = [{"source": "prnu", "coefficient": "0.28", "error": "0.01", "coefficient_2d": "0.4",
                "analytic": "0.28", "convention_matching_paper": "2-D", "coefficient_uniform": "0.4",
                "error_uniform": "0.01", "coefficient_2d_uniform": "0.57", "analytic_uniform": "0.4",
                "convention_matching_paper_uniform": "per-axis"},
               {"source": "offsets", "coefficient": "0.22", "error": "0.01", "coefficient_2d": "0.31",
                "analytic": "0.22", "convention_matching_paper": "neither"}]
    quantities = [row.as_dict()["quantity"] for row in reproduction.error_propagation_rows(records)]
    assert len(set(quantities)) == len(quantities) == 6  # prnu: 2 coefficients and 2 requirements; offsets: 2


def test_star_accuracy_shows_the_prf_width_spread_that_neither_calibration_sees(tmp_path):
    """Noiseless, perfect flat and offsets: flat+metrology is exact without a width spread, and a 1% spread
    leaves several 1e-5 pixel (docs/centroids.md); each calibration removes what it targets. A point is a
    product as the sweep's step writes it."""
    exact, spread = (studies.run_point("star_accuracy", {"detector.prf_width_spread": w}, options={"trials": 200})
                     for w in (0.0, 0.01))
    io.write_product(spread, tmp_path / "point.nc", title="a star-accuracy point")
    error = {mode: float(exact.truth_error.sel(mode=mode)) for mode in exact.mode.values}
    assert error["flat+metrology"] < 1e-5 < 1e-4 < error["flat"] < error["raw"]
    assert float(spread.truth_error.sel(mode="flat+metrology")) > 3e-5
    assert float(exact.accuracy_position.sel(mode="flat+metrology")) < float(exact.accuracy_position.sel(mode="flat"))


@pytest.mark.slow  # two simulated benches and three models: about 40 s on an idle core
def test_tip_tilt_study_pose_and_projective_remove_the_excess_procrustes_cannot(tmp_path):
    """Twin benches with and without the stage's tip-tilt (2e-2 rad peak to valley, 8 positions): Procrustes's
    flat+metrology accuracy grows by far more than the PRF spread's error, the pose and projective models
    remove at least 80% of that excess variance, and the pose's tip and tilt land within their bounds."""
    ds = studies.run_point("tip_tilt", {"stars.tip_tilt_pv": 2e-2, "stars.positions": 8}, options={"trials": 200})
    io.write_product(ds, tmp_path / "point.nc", title="a tip-tilt point")  # as the sweep's step writes it
    excess = dict(zip(ds["model"].values, ds["excess_variance"].values))
    assert excess["procrustes"] > 10 * float(ds["accuracy"].sel(model="pose")) ** 2
    for model in ("projective", "pose"):
        assert excess[model] < 0.2 * excess["procrustes"]
    for angle in ("tip", "tilt"):
        bound = float(ds[f"pose_{angle}_crlb"]) if int(ds[f"pose_{angle}_identifiable"]) else np.inf
        assert float(ds[f"pose_{angle}_error"]) < 3 * float(ds[f"pose_{angle}_crlb_nominal_field"])
        assert float(ds[f"pose_{angle}_error"]) < 3 * bound
    assert ds["excess_variance"].attrs["units"] == "pixel^2"
    # what the pose removes, beside what the true tip and tilt and the noise-limited bound allow (issue 27)
    assert float(ds["pose_removal_true_tip_tilt"]) > 0.99
    assert float(ds["pose_removal"]) >= 0.9 * float(ds["pose_removal_bound"]) > 0


# ------------------------------------------------------------------ chromatic pixels (issue 26)

NOISELESS = {"stars.frames": 2, "detector.photon_noise": False, "detector.read_noise": 0.0}


def test_calibrated_at_633_nm_only_flat_and_metrology_leave_a_chromatic_detector_s_stars_off(tmp_path):
    """The effect at the centroids (the CI's quick check; the accuracy's gain is the slow test below): broadband
    stars on a chromatic detector (the default bench's PRNU, offsets and width spread; amplitude 5) and on its
    achromatic twin, both calibrated perfectly at 633 nm with a white flat, noiseless, 12 positions. Against
    truth, flat+metrology leaves 1.5e-4 pixel on the chromatic detector and 5.7e-5 on the twin (measured). The
    point is a product as the sweep's step writes it (every coordinate with its long name and units)."""
    ds = studies.run_point("chromatic", {}, bench={**NOISELESS, "stars.positions": 12},
                           options={"batches": 2, "trials": 100, "wavelengths": [],
                                    "modes": ("flat+metrology", "achromatic flat+metrology")})
    error = dict(zip(ds["mode"].values, ds["truth_error"].values))
    assert error["flat+metrology"] > 2 * error["achromatic flat+metrology"]
    assert error["achromatic flat+metrology"] < 7e-5  # the PRF width spread's, which neither calibration sees
    assert np.isnan(float(ds["gain"])) and ds.sizes["wavelengths"] == 0  # raw and the chromatic mode left out
    io.write_product(ds, tmp_path / "point.nc", title="a chromatic point")


@pytest.mark.slow  # 25 s on 2 shared cores (load 4; 2026-12-05)
def test_calibrated_at_633_nm_only_a_chromatic_detector_gains_less_from_flat_and_metrology():
    """The issue's first claim at library level, the paper's 33 positions 0.17 pixel apart, noiseless: the twin's
    flat+metrology gain over raw (p) is 4.5, the chromatic detector's 3.2 (measured); asserted below 0.8 of it.
    (12 or 20 positions do not show it: over 2-3 pixels the per-star errors go into the mean shape.)"""
    modes = ("raw", "flat+metrology", "achromatic raw", "achromatic flat+metrology")
    ds = studies.run_point("chromatic", {}, bench=NOISELESS,
                           options={"batches": 2, "trials": 200, "wavelengths": [], "modes": modes})
    accuracy = dict(zip(ds["mode"].values, ds["accuracy_position"].values))
    assert accuracy["raw"] / accuracy["flat+metrology"] == pytest.approx(float(ds["gain"]))
    assert float(ds["gain"]) < 0.8 * float(ds["achromatic_gain"])
    assert float(ds["achromatic_gain"]) > 3  # the calibration works on the twin


def test_with_three_wavelengths_the_chromatic_mode_puts_the_stars_where_the_achromatic_twin_s_are():
    """Noiseless, 12 positions, flat-spectrum stars, the true maps at 450, 633 and 800 nm: against truth the
    chromatic mode leaves 5.9e-5 pixel, the twin's flat+metrology 5.75e-5 (its PRF width spread) and 633 nm alone
    1.6e-4 (measured)."""
    ds = studies.run_point("chromatic", {}, bench={**NOISELESS, "stars.positions": 12},
                           options={"batches": 2, "trials": 100, "wavelengths": [3],
                                    "modes": ("flat+metrology", "achromatic flat+metrology")})
    error = dict(zip(ds["mode"].values, ds["truth_error"].values))
    chromatic = float(ds["chromatic_truth_error"].sel(wavelengths=3))
    assert chromatic < 1.1 * error["achromatic flat+metrology"]
    assert chromatic < 0.5 * error["flat+metrology"]


@pytest.mark.slow  # 2 x 50 s on 2 shared cores (load 4; 2026-12-05)
@pytest.mark.parametrize("spectrum", ["flat", "cool"])
def test_with_three_wavelengths_the_chromatic_mode_is_within_1_2_of_the_achromatic_twin(spectrum):
    """The issue's second claim at library level: the study's bench (33 positions, the paper's photon limit of
    3e-5 pixel a position, amplitude 5), perfect calibrations at 450, 633 and 800 nm. The chromatic mode's (p)
    accuracy over the twin's flat+metrology's (the same noise draws) was 1.03 (flat) and 1.08 (cool) where 633 nm
    alone gave 2.1 and 5.8; and the twin's own gain is the larger."""
    ds = studies.run_point("chromatic", {"stars.spectrum": spectrum}, options={"trials": 300, "wavelengths": [3]})
    accuracy = dict(zip(ds["mode"].values, ds["accuracy_position"].values))
    assert float(ds["chromatic_over_achromatic"].sel(wavelengths=3)) < 1.2
    assert accuracy["flat+metrology"] > 1.5 * accuracy["achromatic flat+metrology"]
    assert float(ds["gain"]) < 0.8 * float(ds["achromatic_gain"])
    assert 2.5e-5 < float(ds["photon_limit"]) < 3.5e-5  # the paper's photon limit a position


def test_on_an_achromatic_detector_the_chromatic_mode_with_noisy_calibrations_is_no_worse_than_flat_and_metrology():
    """Every wavelength's maps the same but for their own noise (offsets 5e-5 pixel and widths 8e-5 pixel a
    pixel, the default bench's floors at 4000 frames; sensitivities 1e-4, a flat's): the chromatic mode takes a
    weighted mean of the three wavelengths' maps, whose noise is below one pair's, and the widths' change it adds
    is noise about zero. Against truth, noiseless flat-spectrum stars, 12 positions: no worse than
    flat+metrology (measured 6.21e-5 against 6.47e-5 pixel)."""
    from types import SimpleNamespace

    import xarray as xr

    from dice_core import chromatic

    bench = studies.apply_overrides(studies.CHROMATIC_BENCH, {**NOISELESS, "stars.positions": 12,
                                                              "chromatic.amplitude": 0.0})
    cfg, truth, manifest, positions, stacks = studies.simulated_stacks(bench, batches=2, label="achromatic")
    rng = np.random.default_rng(26)
    calibration = (633e-9, 450e-9, 800e-9)

    def noisy(values, sigma):
        return values + sigma * rng.standard_normal(values.shape)

    at = {w: truth.sel(wavelength=w) for w in calibration}
    offsets = {w: xr.Dataset({n: (("row", "col"), noisy(at[w][f"{n}_wavelength"].values, 5e-5)) for n in ("dx", "dy")})
               for w in calibration}
    widths = {w: SimpleNamespace(**{f"width_{a}": noisy(at[w][f"width_{a}_wavelength"].values, 8e-5) for a in "xy"})
              for w in calibration}
    sensitivity = {w: noisy(at[w]["sensitivity_wavelength"].values, 1e-4) for w in calibration}
    product = chromatic.chromatic_dataset(calibration, offsets=offsets, widths=widths, sensitivity=sensitivity,
                                          pairs={w: str(w) for w in calibration}, flats={}, reference=633e-9)
    white = noisy(truth["sensitivity"].values, 1e-4)
    spectrum = (manifest.spectrum.wavelength, manifest.spectrum.weight)
    calibrations = {"flat+metrology": {"prnu": white, "dx": offsets[633e-9]["dx"].values,
                                       "dy": offsets[633e-9]["dy"].values},
                    "chromatic": chromatic.star_calibration(product, spectrum, white_prnu=white)}
    _, errors = studies._mode_centroids(truth, manifest, positions, stacks, calibrations, method="gaussian",
                                        half_size=7, label="achromatic")
    assert errors["chromatic"] <= errors["flat+metrology"]


def test_the_chromatic_study_s_rows_set_each_gain_beside_the_paper_s_2_2():
    import xarray as xr

    def point(amplitude, spectrum, gain):
        modes = list(studies.CHROMATIC_MODES)
        accuracy = {"raw": 4e-4, "flat": 2e-4, "flat+metrology": 4e-4 / gain, "achromatic raw": 4e-4,
                    "achromatic flat+metrology": 6e-5}
        return xr.Dataset({"accuracy_position": (("mode",), [accuracy[m] for m in modes]),
                           "error_position": (("mode",), [0.1 * accuracy[m] for m in modes]),
                           "chromatic_over_achromatic": (("wavelengths",), [2.0, 1.5, 1.05, 1.01]),
                           "gain": ((), gain), "achromatic_gain": ((), 4e-4 / 6e-5)},
                          coords={"mode": modes, "wavelengths": [1, 2, 3, 5]},
                          attrs={"amplitude": amplitude, "spectrum": spectrum, "positions": 33})

    rows = reproduction.chromatic_rows([point(5.0, "cool", 1.9), point(2.5, "cool", 2.5), point(5.0, "flat", 3.6)])
    gains = [r.as_dict() for r in rows if r.key == "calibration_gain"]
    assert [g["paper"] for g in gains] == [2.2] * 5  # three points and two twins, beside the paper's 2.2
    assert gains[0]["quantity"] == ("accuracy gain of flat and metrology over raw (p) (chromatic detector of amplitude "
                                    "2.5, cool stars, 33 positions, calibrated at 633 nm)")
    assert gains[0]["error"] == pytest.approx(2.5 * np.hypot(0.1, 0.1))
    assert sum("its achromatic twin" in g["quantity"] for g in gains) == 2
    ratios = [r.as_dict() for r in rows if r.key is None]
    assert len(ratios) == 12 and all(r["unit"] == "1" and r["paper"] != r["paper"] for r in ratios)  # NaN: none
    reproduction.comparison_csv(rows)  # one row per quantity
