"""Dark and PRNU maps against the simulated truth, and the streaming statistics against numpy."""

import numpy as np
import pytest

from dice_core import calibration, simulation
from dice_core.calibration import (TemporalStatistics, area_rms, dark_maps, prnu_difference, prnu_map, remove_gradient,
                                   row_bands)
from dice_core.io import Chunk, FrameStream, read_product
from dice_core.manifest import Detector, load_manifest


def test_temporal_statistics_match_numpy_whatever_the_chunking(rng):
    frames = rng.normal(1000.0, 5.0, size=(101, 4, 5))
    valid = rng.random(frames.shape) > 0.1
    for chunk, band_samples in [(1, None), (7, None), (101, None), (7, 1), (7, 7 * 5 * 2 + 3), (101, 101 * 5)]:
        stats = TemporalStatistics((4, 5))  # bands of 1 row, of 2 rows and a remainder, of 1 row of 101 frames
        for start in range(0, 101, chunk):  # each chunk in bands of rows, as dark_maps and prnu_map take it
            block, ok = frames[start:start + chunk], valid[start:start + chunk]
            for rows in row_bands(block.shape[0], block.shape[1:], samples=band_samples):
                stats.update_rows(rows, block[:, rows], ok[:, rows])
        masked = np.ma.masked_array(frames, ~valid)
        np.testing.assert_allclose(stats.mean, masked.mean(axis=0).data, rtol=1e-13)
        np.testing.assert_allclose(stats.variance, masked.var(axis=0, ddof=1).data, rtol=1e-10)
        np.testing.assert_array_equal(stats.masked, (~valid).sum(axis=0))


DEFECTIVE = Detector(shape=(37, 29), science_rows=(2, 35), science_cols=(3, 27), gain=10.0, saturation=60000.0)


def defective_frames(rng, *, level, frames=23):
    """Frames (frame, row, col) of DEFECTIVE at ``level`` adu with noise, a dead column and a dead pixel (5% of
    the light), a pixel saturated in frames 0-5 only and one at the saturation level (about half its samples)."""
    sensitivity = 1 + 2e-3 * rng.standard_normal(DEFECTIVE.shape)
    sensitivity[:, 11] = sensitivity[20, 5] = 0.05
    data = level * sensitivity * (1 + 0.01 * np.arange(29) / 29) + 5 * rng.standard_normal((frames, 37, 29))
    data[:6, 7, 8] = 65000.0
    data[:, 30, 20] = DEFECTIVE.saturation + 5 * rng.standard_normal(frames)
    return data


def chunks_of(frames, size):
    """io.Chunk's of ``size`` frames as FrameStream yields them (an unsaturated chunk's mask a read-only view)."""
    chunks = []
    for start in range(0, len(frames), size):
        block = frames[start:start + size]
        saturated = block >= DEFECTIVE.saturation
        if not saturated.any():
            saturated = np.broadcast_to(np.False_, block.shape)
        chunks.append(Chunk(start, block, saturated, bool(saturated.any())))
    return chunks


def calibration_maps(dark_frames, flat_frames, chunk):
    """The dark maps and the PRNU map of the frames, in chunks of ``chunk`` frames."""
    dark = dark_maps(chunks_of(dark_frames, chunk), DEFECTIVE)
    flat = prnu_map(chunks_of(flat_frames, chunk), dark["dark"].values, dark_noise=dark["noise"].values,
                    detector=DEFECTIVE)
    return dark, flat


def test_the_maps_do_not_depend_on_the_bands_of_rows_nor_beyond_rounding_on_the_chunks(rng, monkeypatch):
    """Saturated samples (in some chunks only), a dead column and a dead pixel: bands of one row, of 3 rows
    and a remainder, or of one chunk whole (as before the bands) give the maps bit for bit; the design of the
    illumination fit in blocks of 5 pixels too; chunks of 1, 6 or 23 frames, the same but for rounding (1e-12
    of each map's largest value: the pixel at the saturation in the dark and the flat has no signal left)."""
    dark_frames, flat_frames = defective_frames(rng, level=1000.0), defective_frames(rng, level=20000.0)
    monkeypatch.setattr(calibration, "BAND_SAMPLES", 10**9)
    whole = {chunk: calibration_maps(dark_frames, flat_frames, chunk) for chunk in (1, 6, 23)}
    dark, flat = whole[6]
    assert int(dark["saturated_count"].sum()) > 6 and int(flat["saturated_samples"]) > 6
    assert int(flat["n_not_responding"]) == 33 + 1 + 1  # the column, the pixel, the one at the saturation in both
    for samples, design_pixels in [(1, 5), (6 * 29 * 3, 10**9), (6 * 29 * 3 + 1, 7)]:
        monkeypatch.setattr(calibration, "BAND_SAMPLES", samples)
        monkeypatch.setattr(calibration, "DESIGN_PIXELS", design_pixels)
        for chunk in (1, 6, 23):
            banded = calibration_maps(dark_frames, flat_frames, chunk)
            for before, after in zip(whole[chunk], banded):
                assert before.identical(after), (samples, chunk)
    for chunk in (1, 23):
        for before, after in zip(whole[6], whole[chunk]):
            for name in before.data_vars:
                scale = np.nanmax(np.abs(before[name].values)) if before[name].size else 0  # (pixels of no signal)
                np.testing.assert_allclose(after[name].values, before[name].values, rtol=1e-12, atol=1e-12 * scale,
                                           err_msg=name)


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_remove_gradient_gives_the_whole_designs_bits(rng, degree):
    """The illumination fit formed from the design of the used pixels only, a block at a time, gives the
    fit of the whole map's design (np.indices, then the used rows), bit for bit."""
    from dice_core.polynomials import polynomial_design

    image = 3.0 + 0.01 * rng.standard_normal((61, 47))
    mask = rng.random(image.shape) > 0.2
    image[5, :] = np.nan
    rows, cols = np.indices(image.shape)
    design = polynomial_design(cols.ravel(), rows.ravel(), degree=degree)
    use = mask & np.isfinite(image)
    coef, *_ = np.linalg.lstsq(design[use.ravel()], image[use], rcond=None)
    surface = (design @ coef).reshape(image.shape)
    flat, fitted = remove_gradient(image, mask, degree=degree)
    np.testing.assert_array_equal(fitted, surface)
    np.testing.assert_array_equal(flat, image / surface)


@pytest.mark.parametrize("step", ["dark", "prnu"])
def test_a_chunk_is_worked_on_a_band_of_rows_at_a_time(rng, step):
    """dark_maps and prnu_map on one chunk of 128 frames of 256x256 pixels (8.4e6 samples; the chunk itself,
    64 MiB of float64, made before the trace): traced peak measured 37 and 49 MiB (4.7 and 6.2 bytes a sample)
    in bands of BAND_SAMPLES, 204 and 269 MiB (25 and 34 bytes a sample) when the chunk's arithmetic was done
    whole; a change that forms chunk-sized temporaries again fails here."""
    import tracemalloc

    detector = Detector(shape=(256, 256), science_rows=(2, 254), science_cols=(3, 253), gain=10.0,
                        saturation=60000.0)
    level = 1000.0 if step == "dark" else 20000.0
    frames = level + 5.0 * rng.standard_normal((128, 256, 256))
    frames[:, 5, 7] = 60000.0
    chunks = [Chunk(0, frames, frames >= 60000.0, True)]
    dark = np.full(detector.shape, 1000.0)
    tracemalloc.start()
    try:
        if step == "dark":
            maps = dark_maps(chunks, detector)
        else:
            maps = prnu_map(chunks, dark, dark_noise=dark * 0 + 4.0, detector=detector)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 12 * frames.size, peak
    finite = np.isfinite(maps["noise" if step == "dark" else "prnu"].values)
    assert finite.sum() == 252 * 250 - 1 and not finite[5, 7]  # the pixel saturated in every frame: none


def test_the_illumination_fit_holds_its_design_once(rng):
    """remove_gradient on 600x600 pixels (degree 1: 3 terms): traced peak about 34 bytes a pixel (the used
    pixels' design, 24, and their values), against 89 when it formed the whole map's coordinates and design
    and then the used pixels' copy of it."""
    import tracemalloc

    image = 1 + 0.01 * rng.standard_normal((600, 600))
    mask = rng.random(image.shape) > 0.1
    tracemalloc.start()
    try:
        remove_gradient(image, mask, degree=1)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 48 * image.size, peak / image.size


@pytest.mark.parametrize("degree", [0, 1, 2])
def test_remove_gradient_recovers_a_pattern_times_a_polynomial(rng, degree):
    rows, cols = np.indices((30, 40))
    surface = {0: 3.0 + 0 * rows, 1: 3.0 + 0.01 * cols - 0.02 * rows,
               2: 3.0 + 0.01 * cols - 0.02 * rows + 1e-4 * cols * rows}[degree]
    mask = np.ones((30, 40), bool)
    flat, fitted = remove_gradient(surface, mask, degree=degree)
    np.testing.assert_allclose(flat, 1.0, atol=1e-12)
    np.testing.assert_allclose(fitted, surface, rtol=1e-12)
    with pytest.raises(ValueError, match="degree"):
        remove_gradient(surface, mask, degree=-1)


def truth_prnu(truth, detector, degree=1):
    """The simulated sensitivity with the same illumination surface removed, mean 1 over the science area."""
    flat, _ = remove_gradient(truth["sensitivity"].values, detector.science_mask(), degree=degree)
    return flat / np.mean(flat[detector.science_slices])


@pytest.fixture(scope="module")
def dark(calibration_dataset):
    manifest, _ = calibration_dataset
    return dark_maps(FrameStream(manifest.dark, manifest.detector, chunk_frames=300), manifest.detector)


def test_dark_noise_matches_simulated_read_noise_within_5_percent(calibration_dataset, dark):
    manifest, truth = calibration_dataset
    sl = manifest.detector.science_slices
    ratio = dark["noise"].values[sl] / truth["read_noise"].values[sl]
    # 5000 frames: each pixel's noise is estimated to 1%, so 5% per pixel is a 5-sigma bound
    assert np.all(np.abs(ratio - 1) < 0.05), np.abs(ratio - 1).max()
    assert np.mean(ratio) == pytest.approx(1.0, abs=0.005)


def test_dark_mean_matches_bias(calibration_dataset, dark):
    manifest, truth = calibration_dataset
    sl = manifest.detector.science_slices
    error = dark["dark"].values[sl] - truth["bias"].values[sl]
    expected = truth["read_noise"].values[sl] / np.sqrt(int(dark["n_frames"]))
    assert np.sqrt(np.mean(error**2)) < 1.5 * np.sqrt(np.mean(expected**2))


def test_maps_are_nan_outside_the_science_area(calibration_dataset, dark):
    manifest, _ = calibration_dataset
    outside = ~manifest.detector.science_mask()
    assert np.isnan(dark["dark"].values[outside]).all() and np.isnan(dark["noise"].values[outside]).all()
    assert np.isfinite(dark["dark"].values[~outside]).all()


@pytest.fixture(scope="module")
def prnus(calibration_dataset, dark):
    manifest, _ = calibration_dataset
    return {flat: prnu_map(FrameStream(acq, manifest.detector, chunk_frames=128), dark["dark"].values,
                           dark_noise=dark["noise"].values, detector=manifest.detector, label=flat)
            for flat, acq in manifest.flats.items()}


def test_prnu_matches_sensitivity_within_1_5_photon_noise_limit(calibration_dataset, prnus):
    manifest, truth = calibration_dataset
    sl = manifest.detector.science_slices
    expected = truth_prnu(truth, manifest.detector)
    for flat, prnu in prnus.items():
        error = prnu["prnu"].values[sl] - expected[sl]
        limit = float(prnu["photon_noise_limit_rms"])
        assert np.sqrt(np.mean(error**2)) < 1.5 * limit, flat
        # the limit is real: the error is not far below it either (the test could fail both ways)
        assert np.sqrt(np.mean(error**2)) > 0.7 * limit, flat
        # the reported limit agrees with the scatter actually measured in the frames
        measured = np.sqrt(np.nanmean(prnu["temporal_error"].values[sl] ** 2))
        assert measured == pytest.approx(limit, rel=0.1)
        assert np.nanmean(prnu["prnu"].values[sl]) == pytest.approx(1.0, abs=1e-12)


def test_prnu_removes_each_fibers_gradient(calibration_dataset, prnus):
    manifest, truth = calibration_dataset
    sl = manifest.detector.science_slices
    for flat, prnu in prnus.items():
        illumination = truth["flat_illumination"].sel(flat=flat).values
        # the removed surface follows the fiber's illumination (up to the sensitivity's own plane)
        removed = prnu["illumination"].values[sl]
        assert np.corrcoef(removed.ravel(), illumination[sl].ravel())[0, 1] > 0.99


def test_prnu_difference_at_photon_noise_limit(calibration_dataset, prnus):
    manifest, _ = calibration_dataset
    a, b = prnus["fiber_a"], prnus["fiber_b"]
    diff = prnu_difference(a, b, detector=manifest.detector)
    assert float(diff["difference_rms"]) == pytest.approx(float(diff["photon_noise_limit_rms"]), rel=0.2)
    assert float(diff["difference_rms"]) == pytest.approx(area_rms(b["prnu"].values - a["prnu"].values,
                                                                   manifest.detector))


def test_prnu_of_a_dark_frame_is_refused(calibration_dataset, dark):
    manifest, _ = calibration_dataset
    with pytest.raises(ValueError, match="no positive signal"):
        prnu_map(FrameStream(manifest.dark, manifest.detector), dark["dark"].values, dark_noise=dark["noise"].values,
                 detector=manifest.detector)


def test_dead_hot_dust_and_column_defects_are_flagged_and_counted(tmp_path, caplog):
    """Simulated defects (3 dead pixels, 1 dead column, 4 hot pixels, the 6 dust pixels) found from the dark
    and the reference flat's PRNU, each class counted; nothing else flagged. The PRNU leaves the dead pixels
    out of its illumination fit and normalisation, and stays at its photon limit on the others."""
    from conftest import small_config

    cfg = small_config(detector={"dead_pixels": 3, "dead_columns": 1, "hot_pixels": 4},
                       dark={"frames": 200}, flats={"frames": 200})
    path = simulation.simulate_dataset(cfg, tmp_path / "raw")
    manifest, truth = load_manifest(path), read_product(path.parent / "truth.nc")
    dark = calibration.dark_maps(FrameStream(manifest.dark, manifest.detector), manifest.detector)
    with caplog.at_level("WARNING"):
        flat = calibration.prnu_map(FrameStream(manifest.flats["fiber_a"], manifest.detector), dark["dark"].values,
                                    dark_noise=dark["noise"].values, detector=manifest.detector, label="flat fiber_a")
    prnu = flat["prnu"].values
    assert int(flat["n_not_responding"]) == 3 + 37
    assert "flat fiber_a: 40 pixel(s) respond to less than 50% of the median level" in caplog.text
    responding = manifest.detector.science_mask() & ((truth["bad_pixel"].values & simulation.BAD_DEAD) == 0)
    expected, _ = remove_gradient(truth["sensitivity"].values, responding)
    expected /= expected[responding].mean()
    error = (prnu - expected)[responding]
    assert np.sqrt(np.mean(error**2)) < 1.5 * float(flat["photon_noise_limit_rms"])
    assert float(flat["prnu_rms"]) < 0.01  # the dead pixels (PRNU about 0) not in it
    mask = calibration.bad_pixel_mask(dark, prnu, detector=manifest.detector)
    flags, true = mask["bad_pixel"].values, truth["bad_pixel"].values
    flag = calibration.BAD_PIXEL_FLAGS
    dead = (flags & flag["dead"]) > 0
    np.testing.assert_array_equal(dead, (true & simulation.BAD_DEAD) > 0)
    np.testing.assert_array_equal((flags & flag["hot"]) > 0, (true & simulation.BAD_HOT) > 0)
    (column,) = mask["bad_columns"].values
    assert dead[slice(*cfg.detector.science_rows), column].all() and int(mask["n_column"]) == 37
    assert int(mask["n_dead"]) == 3 + 37 and int(mask["n_hot"]) == 4
    # dust: every simulated dust pixel (1.5-5% of light lost) is found; beyond them, the rule may also
    # take a neighbour in the deepest shadows, as it does on the true sensitivities, but for a couple near
    # the threshold that the flat's photon noise (1.6e-4 here) tips either way
    dust = (flags & flag["dust"]) > 0
    centres = (true & simulation.BAD_DUST) > 0
    assert centres.sum() == cfg.detector.dust_pixels and dust[centres].all()
    true_rule = calibration.bad_pixel_mask(dark, truth["sensitivity"].values,
                                           detector=manifest.detector)["bad_pixel"].values
    assert np.sum(dust != ((true_rule & flag["dust"]) > 0)) <= 2
    assert int(mask["n_dust"]) == dust.sum()
    assert np.all(flags[~manifest.detector.science_mask()] == 0)
    assert mask["bad_pixel"].attrs["flag_meanings"] == "dead hot dust column"


@pytest.mark.parametrize("defects, expected", [({"dead_pixels": -1}, "dead_pixels must be >= 0"),
                                               ({"hot_level": -5.0}, "hot_level must be >= 0"),
                                               ({"dead_columns": 1000}, "more defects than the science area")])
def test_impossible_defects_are_refused(defects, expected):
    from conftest import small_config

    with pytest.raises(ValueError, match=expected):
        small_config(detector=defects)


@pytest.mark.parametrize("size, band_samples, bands", [(5, None, 1), (5, 7 * 25 * 53, 6), (3, 1, 37)])
def test_the_local_median_is_scipys_nan_median_filter(size, band_samples, bands, monkeypatch):
    """The bad-pixel mask's local median, vectorised in bands of rows, equals scipy.ndimage.generic_filter with
    np.nanmedian (a Python call a pixel) bit for bit: NaN pixels left out, NaN where a window holds none, even
    counts of valid pixels (the mean of the middle two) and ties."""
    import warnings

    from scipy.ndimage import generic_filter

    rng = np.random.default_rng(7)
    image = rng.normal(1.0, 0.01, (37, 53))
    image[rng.random(image.shape) < 0.15] = np.nan
    image[:4] = np.nan  # windows wholly outside the valid pixels
    image[:, -3:] = np.nan
    image[10:20, 10:20] = np.round(image[10:20, 10:20], 2)  # ties
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        expected = generic_filter(image, np.nanmedian, size=size, mode="constant", cval=np.nan)
    if band_samples is not None:  # bands of a few rows, or of one
        monkeypatch.setattr(calibration, "BAND_SAMPLES", band_samples)
    assert len(calibration.row_bands(size * size, image.shape)) == bands  # (37 rows)
    got = calibration._local_median(image, size)
    assert np.isnan(got[0, 0]) and np.isfinite(got[20, 20])
    np.testing.assert_array_equal(got, expected)
