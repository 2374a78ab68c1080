"""Centroids against truth: the Gaussian fit, Fourier resampling, the pixel-offset correction, the
Cramer-Rao bound, and the reference implementations (scikit-image, photutils, astropy)."""

from pathlib import Path

import numpy as np
import pytest
from astropy.modeling import fitting, models
from photutils.centroids import centroid_2dg
from skimage.registration import phase_cross_correlation

from dice_core import centroids, stacks
from dice_core.detector import PixelResponse

SHAPE = (40, 44)
PSF_SIGMA = 1.3  # pixel, the simulator's
GAIN, READ_NOISE, FLUX, BACKGROUND = 10.0, 4.0, 2.5e5, 10.0  # e-/adu, adu, adu per star, adu per pixel
HALF = 7


def detector(dx=0.0, dy=0.0):
    """Perfect pixels (the simulator's PRF, no offsets) unless offsets are given."""
    ones = np.ones(SHAPE)
    return PixelResponse(ones, ones * dx, ones * dy, 0.3 * ones, 0.3 * ones, 4.0, 0.5)


def star(response, x, y, half=HALF):
    window = centroids.star_window(y, x, half_size=half, shape=SHAPE)
    return window, FLUX * response.gaussian_response(x, y, PSF_SIGMA)[window.slices]


def positions(rng, n=10):
    return [(20 + rng.uniform(-3, 3), 20 + rng.uniform(-3, 3)) for _ in range(n)]


def origin_shift(window, reference):
    return np.array([window.col0 - reference.col0, window.row0 - reference.row0])


def test_window_is_centred_and_refused_at_the_edge():
    window = centroids.star_window(10.4, 20.6, half_size=3, shape=SHAPE)
    assert (window.row0, window.col0, window.size) == (7, 18, 7)
    x, y = window.grid()
    assert (x[0, 0], y[0, 0], x[-1, -1], y[-1, -1]) == (18, 7, 24, 13)
    with pytest.raises(centroids.WindowError, match=r"star 3 at position 12: its 15x15 window .* leaves"):
        centroids.star_window(5.0, 20.0, half_size=7, shape=SHAPE, label="star 3 at position 12")


def test_a_window_outside_the_science_area_and_an_area_too_small_are_said_with_the_star_and_the_key():
    """The dark is measured in the science area only: a window reaching past it held NaN, and the fit said
    "no signal above the background in the window", naming neither the star nor the cause."""
    area = ((10, 30), (5, 40))
    assert centroids.star_window(15.0, 20.0, half_size=4, shape=SHAPE, area=area).row0 == 11
    with pytest.raises(centroids.WindowError, match=r"^star 2 at position 7: its 9x9 window around row 12.0, col "
                                                    r"20.0 \(rows 8-16, cols 16-24\) leaves the science area, rows "
                                                    r"10-29 and cols 5-39"):
        centroids.star_window(12.0, 20.0, half_size=4, shape=SHAPE, area=area, label="star 2 at position 7")
    from dice_core.manifest import Detector

    narrow = Detector(shape=SHAPE, science_rows=(10, 12), science_cols=(4, 43), gain=GAIN, saturation=65535.0)
    assert centroids.science_area_problem(narrow, 4) == ("detector.science_area holds 2 row(s) x 39 col(s), too few "
                                                         "for the 9x9 star windows of centroids.half_size 4")
    assert centroids.science_area_problem(narrow, 0) is None
    window = centroids.Window(3, 4, 5)
    with pytest.raises(centroids.WindowError, match=r"^star 1 at position 2: no signal above the background in its "
                                                    r"window \(rows 3-7, cols 4-8\)"):
        centroids.gaussian_fit(np.zeros((5, 5)), window, label="star 1 at position 2")


def test_noiseless_perfect_pixels_both_methods_better_than_1e_6_pixel(rng):
    response = detector()
    reference_xy = (20.3, 19.6)
    ref_window, ref_image = star(response, *reference_xy)
    ref_fit = centroids.gaussian_fit(ref_image, ref_window)
    assert ref_fit.width_x == pytest.approx(1.32, abs=0.01) and ref_fit.width_y == pytest.approx(1.32, abs=0.01)
    for xy in positions(rng):
        truth = np.subtract(xy, reference_xy)
        window, image = star(response, *xy)
        fit = centroids.gaussian_fit(image, window)
        assert np.abs([fit.x - ref_fit.x, fit.y - ref_fit.y] - truth).max() < 1e-6
        shift = centroids.fourier_displacement(ref_image, image) + origin_shift(window, ref_window)
        assert np.abs(shift - truth).max() < 1e-6


def test_fourier_displacement_between_stars_of_different_flux_and_background():
    response = detector()
    ref_window, ref_image = star(response, 20.3, 19.6)
    window, image = star(response, 24.71, 16.18)
    image = 0.37 * image + 25.0  # a fainter star on a brighter background
    shift = centroids.fourier_displacement(ref_image, image) + origin_shift(window, ref_window)
    np.testing.assert_allclose(shift, [24.71 - 20.3, 16.18 - 19.6], atol=1e-6)
    with pytest.raises(ValueError, match="odd sides"):
        centroids.fourier_displacement(np.ones((4, 4)), np.ones((4, 4)))


def test_offset_correction_removes_the_error_of_pixel_offsets(rng):
    dx, dy = 1e-3 * rng.standard_normal(SHAPE), 1e-3 * rng.standard_normal(SHAPE)
    response = detector(dx, dy)
    reference_xy = (20.3, 19.6)
    ref_window, ref_raw = star(response, *reference_xy)
    ref_corrected = centroids.offset_corrected(ref_raw, dx[ref_window.slices], dy[ref_window.slices])
    raw_errors, corrected_errors = [], []
    for xy in positions(rng):
        truth = np.subtract(xy, reference_xy)
        window, raw = star(response, *xy)
        corrected = centroids.offset_corrected(raw, dx[window.slices], dy[window.slices])
        shift = origin_shift(window, ref_window)
        for images, errors in (((ref_raw, raw), raw_errors), ((ref_corrected, corrected), corrected_errors)):
            fits = [centroids.gaussian_fit(image, w) for image, w in zip(images, (ref_window, window))]
            errors.append([fits[1].x - fits[0].x - truth[0], fits[1].y - fits[0].y - truth[1]])
            errors.append(centroids.fourier_displacement(*images) + shift - truth)
    raw_rms, corrected_rms = np.sqrt(np.mean(np.square(raw_errors))), np.sqrt(np.mean(np.square(corrected_errors)))
    assert raw_rms > 1e-4  # offsets of 1e-3 pixel move a centroid by a few 1e-4
    assert corrected_rms < 1e-6


@pytest.fixture(scope="module")
def noisy_draws():
    """400 photon- and read-noise draws of one star window (the simulator's flux and noise)."""
    rng = np.random.default_rng(3)
    window, image = star(detector(), 20.3, 19.6)
    clean = image + BACKGROUND
    draws = [rng.poisson(clean * GAIN) / GAIN + READ_NOISE * rng.standard_normal(clean.shape) for _ in range(400)]
    weights = 1 / np.sqrt(clean / GAIN + READ_NOISE**2)
    return window, clean, draws, weights


def test_photon_noise_precision_at_the_cramer_rao_bound(noisy_draws):
    window, clean, draws, weights = noisy_draws
    bound = centroids.cramer_rao(centroids.gaussian_fit(clean, window), window, gain=GAIN, read_noise=READ_NOISE)
    gaussian = np.array([[f.x, f.y] for f in (centroids.gaussian_fit(d, window, weights=weights) for d in draws)])
    fourier = np.array([centroids.fourier_displacement(clean, d, weights=weights) for d in draws])
    for estimates in (gaussian, fourier):
        # 400 draws: the scatter itself is known to 3.5%
        np.testing.assert_allclose(estimates.std(axis=0), bound, rtol=0.1)
    # unweighted, both are about 1.3x above the bound for a star this bright
    unweighted = np.array([centroids.fourier_displacement(clean, d) for d in draws[:100]])
    assert np.all(unweighted.std(axis=0) > 1.15 * bound)


def test_fourier_resampling_beats_phase_cross_correlation(rng):
    response = detector()
    ref_window, ref_image = star(response, 20.3, 19.6)
    errors = {"ours": [], "skimage": [], "skimage x100": []}
    for x, y in positions(rng, 5):
        # the same window origin, so that every method measures the shift within the window
        window = ref_window
        image = FLUX * response.gaussian_response(x, y, PSF_SIGMA)[window.slices]
        truth = np.array([x - 20.3, y - 19.6])
        errors["ours"].append(centroids.fourier_displacement(ref_image, image) - truth)
        for name, factor in (("skimage", 1), ("skimage x100", 100)):
            # skimage returns the shift that registers the moving image onto the reference, (row, col)
            shift, _, _ = phase_cross_correlation(image, ref_image, upsample_factor=factor)
            errors[name].append(np.array([shift[1], shift[0]]) - truth)
    worst = {name: np.abs(e).max() for name, e in errors.items()}
    assert worst["ours"] < 1e-6
    # skimage: whole pixels at its default, about 0.02 pixel at 100 (its phase normalisation on a
    # 15-pixel window); ours is over 10,000 times more accurate than either
    assert worst["ours"] < worst["skimage x100"] / 1e4 and worst["skimage x100"] < worst["skimage"]


def test_gaussian_fit_agrees_with_photutils_and_astropy(noisy_draws):
    window, clean, draws, weights = noisy_draws
    bound = centroids.cramer_rao(centroids.gaussian_fit(clean, window), window, gain=GAIN, read_noise=READ_NOISE)
    y, x = np.mgrid[:window.size, :window.size]
    fitter = fitting.LevMarLSQFitter()
    for image in draws[:10]:
        ours = centroids.gaussian_fit(image, window)
        ours_xy = np.array([ours.x - window.col0, ours.y - window.row0])
        # photutils fits a Gaussian2D plus a constant to the same pixels
        np.testing.assert_allclose(centroid_2dg(image), ours_xy, atol=0.2 * bound.max())
        start = models.Gaussian2D(ours.intensity, *ours_xy, 1.3, 1.3) + models.Const2D(ours.background)
        theirs = fitter(start, x, y, image, maxiter=500)
        np.testing.assert_allclose([theirs.x_mean_0.value, theirs.y_mean_0.value], ours_xy, atol=1e-3 * bound.max())


def test_flat_correction_removes_the_error_of_prnu(rng):
    sensitivity = 1 + 2e-3 * rng.standard_normal(SHAPE)
    ones = np.ones(SHAPE)
    response = PixelResponse(sensitivity, 0 * ones, 0 * ones, 0.3 * ones, 0.3 * ones, 4.0, 0.5)
    reference_xy = (20.3, 19.6)
    ref_window, ref_raw = star(response, *reference_xy)
    raw_errors, flat_errors = [], []
    for xy in positions(rng):
        truth = np.subtract(xy, reference_xy)
        window, raw = star(response, *xy)
        shift = origin_shift(window, ref_window)
        raw_errors.append(centroids.fourier_displacement(ref_raw, raw) + shift - truth)
        flat = (ref_raw / sensitivity[ref_window.slices], raw / sensitivity[window.slices])
        flat_errors.append(centroids.fourier_displacement(*flat) + shift - truth)
    assert np.sqrt(np.mean(np.square(raw_errors))) > 1e-5  # PRNU of 2e-3 moves a centroid by a few 1e-5
    assert np.abs(flat_errors).max() < 1e-6


def simulate_stars(path, *, prf_width_spread, prf_slope_rms=0.0, step=None):
    """Simulated positions without noise: the default detector (PRNU 2e-3, offsets 1e-3 pixel)."""
    from dice_core import simulation
    from dice_core.io import read_product
    from dice_core.manifest import load_manifest

    cfg = simulation.SimulationConfig.from_dict({
        "name": "stars-test", "dark": {"frames": 2}, "flats": {"frames": 2},
        "detector": {"photon_noise": False, "read_noise": 0.0, "dtype": "float32",
                     "prf_width_spread": prf_width_spread, "prf_slope_rms": prf_slope_rms},
        "metrology": {"frames": 2, "baselines": {"H1H4": {"period": 2.4, "angle_deg": 2.0}}, "pairs": {}},
        "stars": {"positions": 5, "frames": 4, "flux_rsd": 0.0, **({} if step is None else {"step": step})}})
    manifest = load_manifest(simulation.simulate_dataset(cfg, path))
    return manifest, read_product(path / "truth.nc")


@pytest.fixture(scope="module")
def star_dataset(tmp_path_factory):
    """Pixels differ by sensitivity and offset only (same PRF width): what the calibrations model."""
    return simulate_stars(tmp_path_factory.mktemp("stars"), prf_width_spread=0.0)


def stacks_of(manifest, n_batches=2, chunks_of=None):
    """Each position's PositionStack, as the workflow's stack_position step makes it."""
    from dice_core.io import FrameStream

    streams = {p.index: FrameStream(p.acquisition, manifest.detector) for p in manifest.positions}
    chunks_of = chunks_of or (lambda index: streams[index])
    return [stacks.stack_position(chunks_of(i), stream.n_frames, n_batches=n_batches, position=i,
                                  label=f"position {i}")
            for i, stream in streams.items()]


def measure(manifest, truth, *, flat, metrology, method="fourier", n_batches=2, stacks=None):
    result = centroids.measure_positions(
        stacks or stacks_of(manifest, n_batches), [p.index for p in manifest.positions], approx=manifest.star_approx,
        detector=manifest.detector, dark=truth["bias"].values, read_noise=np.ones(manifest.detector.shape),
        prnu=truth["sensitivity"].values if flat else None,
        dx=truth["dx"].values if metrology else None, dy=truth["dy"].values if metrology else None,
        method=method)
    return result


def differential_error(result, truth):
    """Centroid errors against truth with each position's common translation removed, rms (pixel)."""
    errors = [result.x - truth["star_x"].values, result.y - truth["star_y"].values]
    return float(np.sqrt(np.mean([np.square(e - e.mean(axis=1, keepdims=True)) for e in errors])))


@pytest.mark.parametrize("method", ["fourier", "gaussian"])
def test_each_calibration_removes_the_error_it_targets(star_dataset, method):
    manifest, truth = star_dataset
    error = {(flat, metrology): differential_error(measure(manifest, truth, flat=flat, metrology=metrology,
                                                           method=method), truth)
             for flat in (False, True) for metrology in (False, True)}
    # PRNU of 2e-3 (with dust) moves the stars by about 1e-3 pixel, offsets of 1e-3 pixel by 2e-4
    assert error[False, False] > 5e-4
    assert error[True, False] < 0.5 * error[False, False]   # the flat takes the PRNU out...
    assert error[True, True] < 0.05 * error[True, False]    # ...the offsets, what the PRNU leaves
    assert error[False, True] < error[False, False]
    assert error[True, True] < 1e-5


def test_pixel_width_spread_is_what_neither_calibration_sees(tmp_path):
    """The simulator's default 1% spread of PRF widths changes how pixels sample a curved PSF:
    neither the flat (integrals) nor the metrology (barycentres) measures it."""
    manifest, truth = simulate_stars(tmp_path, prf_width_spread=0.01)
    error = differential_error(measure(manifest, truth, flat=True, metrology=True), truth)
    assert 2e-5 < error < 2e-4


def test_positions_report_precision_saturation_and_bad_input(star_dataset, caplog):
    manifest, truth = star_dataset
    result = measure(manifest, truth, flat=True, metrology=True)
    assert result.x.shape == (5, 5) and np.all(result.n_frames == 4) and not result.n_saturated.any()
    assert np.all(result.precision_x < 1e-5)  # no noise: the batches agree
    with pytest.raises(ValueError, match="position 1: 4 frame\\(s\\) for 5 batches"):
        measure(manifest, truth, flat=True, metrology=True, n_batches=5)
    with pytest.raises(ValueError, match="unknown centroid method"):
        measure(manifest, truth, flat=True, metrology=True, method="barycentre")
    stacks = stacks_of(manifest)
    with pytest.raises(ValueError, match="no frames given for position 5 \\(4 stack\\(s\\) for 5 positions\\)"):
        measure(manifest, truth, flat=True, metrology=True, stacks=stacks[:-1])
    with pytest.raises(ValueError, match="position 1 has 1 batch; a precision needs two"):
        measure(manifest, truth, flat=True, metrology=True, stacks=stacks_of(manifest, n_batches=1))
    with pytest.raises(ValueError, match="the stack given for position 1 is that of position 2"):
        measure(manifest, truth, flat=True, metrology=True, stacks=[stacks[1], stacks[0], *stacks[2:]])


def test_a_saturated_window_is_refused_counted_and_logged(star_dataset, caplog):
    import logging

    from dice_core.io import Chunk, FrameStream

    manifest, truth = star_dataset
    streams = {p.index: FrameStream(p.acquisition, manifest.detector) for p in manifest.positions}
    row, col = (int(round(v)) for v in manifest.star_approx[2])

    def frames_of(index):
        for chunk in streams[index]:
            if index != 3:
                yield chunk
                continue
            saturated = np.zeros(chunk.frames.shape, bool)
            saturated[0, row, col] = True  # star 2's peak, at position 3
            yield Chunk(chunk.start, chunk.frames, saturated, True)

    log = logging.getLogger("test-centroids")
    positions = list(streams)
    with caplog.at_level("WARNING", logger="test-centroids"):
        result = centroids.measure_positions(
            stacks_of(manifest, chunks_of=frames_of), positions, approx=manifest.star_approx,
            detector=manifest.detector, dark=truth["bias"].values, read_noise=np.ones(manifest.detector.shape),
            log=log)
    assert result.n_saturated[2, 2] == 1 and result.n_saturated.sum() == 1
    assert np.isnan(result.x[2, 2]) and np.isfinite(np.delete(result.x.ravel(), 2 * 5 + 2)).all()
    assert "star 2 at position 3 has 1 saturated sample(s) in its window: not measured" in caplog.text
    # at the first position the window is every later one's reference: refused
    first = next(iter(streams))
    with pytest.raises(ValueError, match="star 2 at position 1: saturated samples in the window every later"):
        centroids.measure_positions(
            stacks_of(manifest, chunks_of=lambda i: frames_of(3) if i == first else streams[i]), positions,
            approx=manifest.star_approx, detector=manifest.detector, dark=truth["bias"].values,
            read_noise=np.ones(manifest.detector.shape))


def test_windows_keep_other_stars_light_out():
    # the ci preset's 16-pixel pattern: a 15x15 window's corner 1 pixel from a neighbour's peak
    tight = ((20.3, 23.0), (12.3, 15.0), (12.3, 31.0), (28.3, 15.0), (28.3, 31.0))
    assert centroids.isolated_half_size(tight, 7, width=1.3) == 4
    wide = ((40.3, 46.0), (20.3, 26.0), (20.3, 66.0), (60.3, 26.0), (60.3, 66.0))  # the default's 40 pixels
    assert centroids.isolated_half_size(wide, 7, width=1.3) == 7


@pytest.mark.parametrize("method", ["fourier", "gaussian"])
def test_a_tight_pattern_is_measured_in_windows_of_one_star(tmp_path, method, caplog):
    """Noiseless ci geometry (40x44, 16-pixel pattern): with 15x15 windows, the neighbours' light cut by
    the window edges held the Fourier method's corner stars 0.1 to 0.6 pixel off (or it did not converge)."""
    import logging

    from dice_core import simulation
    from dice_core.io import read_product
    from dice_core.manifest import load_manifest

    cfg = simulation.SimulationConfig.from_dict({
        "name": "tight-test", "dark": {"frames": 2}, "flats": {"frames": 2},
        "detector": {"shape": [40, 44], "science_rows": [2, 39], "science_cols": [4, 43], "photon_noise": False,
                     "read_noise": 0.0, "dtype": "float32", "prf_width_spread": 0.0},
        "metrology": {"frames": 2, "baselines": {"H1H4": {"period": 2.4, "angle_deg": 2.0}}, "pairs": {}},
        "stars": {"positions": 4, "frames": 4, "flux_rsd": 0.0, "pattern_centre": [23.0, 20.0],
                  "pattern_side": 16.0}})
    manifest = load_manifest(simulation.simulate_dataset(cfg, tmp_path))
    truth = read_product(tmp_path / "truth.nc")
    with caplog.at_level("WARNING", logger="test-tight"):
        result = centroids.measure_positions(
            stacks_of(manifest), [p.index for p in manifest.positions], approx=manifest.star_approx,
            detector=manifest.detector, dark=truth["bias"].values, read_noise=np.ones(manifest.detector.shape),
            prnu=truth["sensitivity"].values, dx=truth["dx"].values, dy=truth["dy"].values, method=method,
            log=logging.getLogger("test-tight"))
    assert "15x15 windows would hold other stars' light" in caplog.text and result.windows.shape == (5, 9, 9)
    errors = np.stack([result.x - truth["star_x"].values, result.y - truth["star_y"].values])
    # 9x9 windows: the neighbours' light at 1.5e-4 of their peak moves the stars by 1e-5 relative to one
    # another (the Fourier method's common 8e-4 is its own wings' cut at 3 sigma, a translation)
    assert np.abs(errors - errors.mean(axis=2, keepdims=True)).max() < 5e-5
    assert np.abs(errors).max() < 2e-3


def test_stars_tied_with_their_references_weights_agree_with_the_gaussian_fits(tmp_path):
    """The 1% PRF width spread moves each star by a fixed amount that depends on how it is weighted: tied
    unweighted but resampled weighted, the Fourier method kept 7.6e-5 pixel of it between stars."""
    manifest, truth = simulate_stars(tmp_path, prf_width_spread=0.01)
    fourier, gaussian = (measure(manifest, truth, flat=True, metrology=True, method=m) for m in ("fourier", "gaussian"))
    difference = np.stack([fourier.x - gaussian.x, fourier.y - gaussian.y])
    assert np.abs(difference - difference.mean(axis=2, keepdims=True)).max() < 1e-5


def test_asymmetric_pixels_are_corrected_at_their_barycentres_not_their_centres(tmp_path):
    """PRFs with a sensitivity slope (rms 0.05 per pixel) move each pixel's barycentre by slope x width^2
    (2e-3 pixel rms): a star sees the barycentres, so the offset correction must use those, which the
    metrology measures to within a few percent (the period-dependent lag, tests/test_fringes.py)."""
    manifest, truth = simulate_stars(tmp_path, prf_width_spread=0.0, prf_slope_rms=0.05)
    flat_only = measure(manifest, truth, flat=True, metrology=False)
    centre = measure(manifest, truth, flat=True, metrology=True)  # truth dx, dy: the PRF centres
    truth_bary = truth.copy()
    truth_bary["dx"], truth_bary["dy"] = truth["barycentre_dx"], truth["barycentre_dy"]
    barycentre = measure(manifest, truth_bary, flat=True, metrology=True)
    error_centre, error_barycentre = (differential_error(r, truth) for r in (centre, barycentre))
    shift = float(np.sqrt(np.mean((truth["barycentre_dx"] - truth["dx"]).values ** 2)))
    assert 1e-3 < shift < 3e-3
    assert 3e-4 < error_centre < differential_error(flat_only, truth) < 1e-3  # 4.5e-4 and 5.7e-4
    assert error_barycentre < 1e-5  # 5e-6


def test_bad_pixels_in_a_star_window_are_left_out_or_the_star_refused(tmp_path, caplog):
    """A dead column through star 1's core (its samples at the dark level): a Gaussian fit without metrology
    leaves it out and keeps the accuracy it has without the defect, where using it costs far more; the Fourier
    method, which resamples the whole window, cannot: the star is not measured, at every position when its
    reference window holds the defect (logged), at that position when only a later window does (NaN and a
    warning), and a defect in the central star's reference window, which ties every star, is an error naming
    the star and the pixel. Dust flags alone change nothing: the flat corrects those pixels."""
    import logging

    from dice_core.calibration import BAD_PIXEL_FLAGS
    from dice_core.io import Chunk, FrameStream

    manifest, truth = simulate_stars(tmp_path, prf_width_spread=0.0, step=[0.0, 0.6])  # windows follow the stars
    positions = [p.index for p in manifest.positions]
    common = dict(approx=manifest.star_approx, detector=manifest.detector, dark=truth["bias"].values,
                  read_noise=np.ones(manifest.detector.shape), prnu=truth["sensitivity"].values)
    args = (positions,)
    clean = {m: centroids.measure_positions(stacks_of(manifest), *args, method=m, **common)
             for m in ("gaussian", "fourier")}
    size = clean["fourier"].windows.shape[-1]
    half = size // 2
    # star 1's windows: the first on its approximate position, each later one on the previous centroid
    centres = [manifest.star_approx[1]] + [(clean["fourier"].y[i, 1], clean["fourier"].x[i, 1])
                                           for i in range(len(positions) - 1)]
    windows = [centroids.star_window(r, c, half_size=half, shape=manifest.detector.shape) for r, c in centres]
    first = windows[0]
    column = first.col0 + half + 1  # through the star's core, next to its peak
    rows = slice(first.row0, first.row0 + size)
    streams = {p.index: FrameStream(p.acquisition, manifest.detector) for p in manifest.positions}

    def dead_column(index):
        for chunk in streams[index]:
            frames = chunk.frames.copy()
            frames[:, rows, column] = truth["bias"].values[rows, column]  # no light: the dark level
            yield Chunk(chunk.start, frames, chunk.saturated, chunk.any_saturated)

    dead = stacks_of(manifest, chunks_of=dead_column)
    flags = np.zeros(manifest.detector.shape, np.int8)
    flags[rows, column] = BAD_PIXEL_FLAGS["dead"] | BAD_PIXEL_FLAGS["column"]
    left_out = centroids.measure_positions(dead, *args, method="gaussian", bad_pixels=flags, **common)
    used = centroids.measure_positions(dead, *args, method="gaussian", **common)
    assert np.all(left_out.n_bad_pixels[:, 1] > 0) and not left_out.n_bad_pixels[:, [0, 2, 3, 4]].any()
    assert differential_error(left_out, truth) < 1.2 * differential_error(clean["gaussian"], truth)
    assert differential_error(used, truth) > 10 * differential_error(left_out, truth)
    assert np.all(left_out.limit_x[:, 1] > clean["gaussian"].limit_x[:, 1])  # a bound without the column
    dust = np.where(flags > 0, BAD_PIXEL_FLAGS["dust"], 0).astype(np.int8)
    assert np.array_equal(centroids.measure_positions(dead, *args, method="gaussian", bad_pixels=dust, **common).x,
                          used.x)
    log = logging.getLogger("test-centroids")
    with caplog.at_level("WARNING", logger="test-centroids"):
        unreferenced = centroids.measure_positions(dead, *args, method="fourier", bad_pixels=flags, log=log, **common)
    assert np.isnan(unreferenced.x[:, 1]).all() and np.isfinite(unreferenced.x[:, [0, 2, 3, 4]]).all()
    assert (f"star 1 at position {positions[0]}: its reference window holds bad pixel(s) row {first.row0}, "
            f"col {column} (dead, column)") in caplog.text
    # star 0, the centre
    central = centroids.star_window(*manifest.star_approx[0], half_size=half, shape=manifest.detector.shape)
    flags_central = np.zeros(manifest.detector.shape, np.int8)
    flags_central[central.row0, central.col0] = BAD_PIXEL_FLAGS["hot"]
    with pytest.raises(centroids.WindowError, match=rf"star 0 at position {positions[0]}: its window, the reference "
                                                     rf"every star is tied to, holds bad pixel\(s\) row "
                                                     rf"{central.row0}, col {central.col0} \(hot\)"):
        centroids.measure_positions(stacks_of(manifest), *args, method="fourier", bad_pixels=flags_central, **common)
    # a pixel only a later window of star 1 holds
    later = [(i, r, c) for i, w in enumerate(windows[1:], 1) for r in range(w.row0, w.row0 + size)
             for c in range(w.col0, w.col0 + size)
             if not (first.row0 <= r < first.row0 + size and first.col0 <= c < first.col0 + size)]
    assert later, "the stars do not move enough between positions for this test"
    i, r, c = later[0]
    flags = np.zeros(manifest.detector.shape, np.int8)
    flags[r, c] = BAD_PIXEL_FLAGS["hot"]
    log = logging.getLogger("test-centroids")
    with caplog.at_level("WARNING", logger="test-centroids"):
        refused = centroids.measure_positions(stacks_of(manifest), *args, method="fourier", bad_pixels=flags,
                                              log=log, **common)
    assert np.isnan(refused.x[i, 1]) and refused.n_bad_pixels[i, 1] == 1
    assert f"star 1 at position {positions[i]} has bad pixel(s) in its window, row {r}, col {c} (hot)" in caplog.text
    assert np.isfinite(refused.x[:, [0, 2, 3, 4]]).all()


def simulate_noisy_stars(path, *, prf_width_spread, frames=400):
    """Simulated positions with photon and read noise (the default detector and stars), 5 positions."""
    from dice_core import simulation
    from dice_core.io import read_product
    from dice_core.manifest import load_manifest

    cfg = simulation.SimulationConfig.from_dict({
        "name": "noisy-stars-test", "dark": {"frames": 2}, "flats": {"frames": 2}, "frames_per_file": 100000,
        "detector": {"prf_width_spread": prf_width_spread},
        "metrology": {"frames": 2, "baselines": {"H1H4": {"period": 2.4, "angle_deg": 2.0}}, "pairs": {}},
        "stars": {"positions": 5, "frames": frames}})
    manifest = load_manifest(simulation.simulate_dataset(cfg, path))
    return manifest, read_product(path / "truth.nc")


def measure_with_widths(manifest, truth, variance_x, variance_y, *, method="gaussian", stacks=None, read_noise=None):
    return centroids.measure_positions(
        stacks or stacks_of(manifest), [p.index for p in manifest.positions], approx=manifest.star_approx,
        detector=manifest.detector, dark=truth["bias"].values,
        read_noise=np.ones(manifest.detector.shape) if read_noise is None else read_noise,
        prnu=truth["sensitivity"].values, dx=truth["dx"].values, dy=truth["dy"].values,
        variance_x=variance_x, variance_y=variance_y, method=method)


def measurable_variances(truth, *, degree=6):
    """The PRF variance deviations the width maps can give: the truth's, off the smooth polynomials."""
    from dice_core import prf

    mask = np.zeros(truth["width_x"].shape, bool)
    mask[2:79, 10:83] = True  # the default science area
    rows, cols = np.nonzero(mask)
    out = []
    for axis in "xy":
        v = np.zeros(mask.shape)
        v[mask] = prf.pixel_scale(truth[f"width_{axis}"].values[mask] ** 2, cols, rows, degree=degree)
        out.append(v)
    return out


def affine_residual_over_bound(result, truth):
    """rms of the errors against truth with each position's affine transform removed, over the rms the
    Cramer-Rao bounds give after the same projection (1 at the bound)."""
    squared, expected = 0.0, 0.0
    for p in range(result.x.shape[0]):
        x, y = truth["star_x"].values[p], truth["star_y"].values[p]
        one, zero = np.ones_like(x), np.zeros_like(x)
        design = np.block([[one[:, None], zero[:, None], x[:, None], y[:, None], zero[:, None], zero[:, None]],
                           [zero[:, None], one[:, None], zero[:, None], zero[:, None], x[:, None], y[:, None]]])
        projector = np.eye(design.shape[0]) - design @ np.linalg.pinv(design)
        error = np.concatenate([result.x[p] - x, result.y[p] - y])
        variance = np.concatenate([result.limit_x[p], result.limit_y[p]]) ** 2
        squared += float(np.sum((projector @ error) ** 2))
        expected += float(np.sum(projector**2 @ variance))  # E|P e|^2 = sum_ij P_ij^2 sigma_j^2
    return np.sqrt(squared / expected)


@pytest.mark.parametrize("method", ["gaussian", pytest.param("fourier", marks=pytest.mark.slow)])
def test_the_width_correction_removes_what_the_width_spread_leaves(tmp_path, method):
    """Noiseless, the default 1% spread: flat+metrology keeps 6e-5 pixel; with the PRF variances the width
    maps can measure (the truth's, off the smooth polynomials), far less."""
    manifest, truth = simulate_stars(tmp_path, prf_width_spread=0.01)
    st = stacks_of(manifest)
    without = differential_error(measure(manifest, truth, flat=True, metrology=True, method=method, stacks=st), truth)
    with_widths = differential_error(measure_with_widths(manifest, truth, *measurable_variances(truth), method=method,
                                                         stacks=st), truth)
    assert 4e-5 < without < 1e-4
    assert with_widths < 1e-5 and with_widths < 0.15 * without, (with_widths, without)


@pytest.fixture(scope="module")
def noisy_stars(tmp_path_factory):
    manifest, truth = simulate_noisy_stars(tmp_path_factory.mktemp("noisy-stars"), prf_width_spread=0.01)
    return manifest, truth, stacks_of(manifest, n_batches=4)


def measure_flat_metrology(manifest, truth, stacks, *, read_noise):
    """Gaussian centroids corrected with the true flat and offsets (no widths)."""
    return centroids.measure_positions(
        stacks, [p.index for p in manifest.positions], approx=manifest.star_approx, detector=manifest.detector,
        dark=truth["bias"].values, read_noise=read_noise, prnu=truth["sensitivity"].values, dx=truth["dx"].values,
        dy=truth["dy"].values, method="gaussian")


def test_with_noise_the_width_correction_reaches_the_cramer_rao_bound(noisy_stars):
    """400 frames per position (bound about 4.4e-5 pixel): the width spread's 6e-5 shows in flat+metrology,
    and the width mode sits at the bound (per-position affine removed)."""
    manifest, truth, st = noisy_stars
    read_noise = truth["read_noise"].values
    base = measure_flat_metrology(manifest, truth, st, read_noise=read_noise)
    widths = measure_with_widths(manifest, truth, *measurable_variances(truth), stacks=st, read_noise=read_noise)
    ratio_base, ratio_width = (affine_residual_over_bound(r, truth) for r in (base, widths))
    assert ratio_width < 1.2, ratio_width
    assert ratio_base > 1.3 * ratio_width, (ratio_base, ratio_width)


def test_without_width_spread_the_width_mode_is_no_worse_than_flat_and_metrology(tmp_path):
    """No width spread: the width maps hold only their noise (drawn at the default preset's stated error,
    8e-5 pixel, tests/test_prf.py), which the correction turns into far less than the photon noise."""
    manifest, truth = simulate_noisy_stars(tmp_path, prf_width_spread=0.0)
    st = stacks_of(manifest, n_batches=4)
    read_noise = truth["read_noise"].values
    base = measure_flat_metrology(manifest, truth, st, read_noise=read_noise)
    zero = np.zeros(manifest.detector.shape)
    exact = measure_with_widths(manifest, truth, zero, zero, stacks=st, read_noise=read_noise)
    np.testing.assert_array_equal(exact.x, base.x)  # no width differences: the offset correction itself
    rng = np.random.default_rng(5)
    noise = [2 * 0.2063 * 8e-5 * rng.standard_normal(manifest.detector.shape) for _ in "xy"]  # pixel^2
    noisy = measure_with_widths(manifest, truth, *noise, stacks=st, read_noise=read_noise)
    ratio_base, ratio_width = (affine_residual_over_bound(r, truth) for r in (base, noisy))
    assert ratio_width < 1.02 * ratio_base, (ratio_base, ratio_width)
    assert ratio_base < 1.2


@pytest.mark.filterwarnings("error::RuntimeWarning")
@pytest.mark.parametrize("method", ["fourier", "gaussian"])
def test_a_pixel_zero_in_every_frame_and_the_dark_is_named(star_dataset, method):
    """Zero signal and zero read noise would give the pixel an infinite weight: an error naming the star, the
    position and the pixel, not the fit's bare "Residuals are not finite", said before dividing by zero (no
    RuntimeWarning)."""
    from dice_core.io import Chunk, FrameStream

    manifest, truth = star_dataset
    row, col = (int(round(v)) for v in manifest.star_approx[2])
    row, col = row + 1, col - 1
    streams = {p.index: FrameStream(p.acquisition, manifest.detector) for p in manifest.positions}

    def zero_pixel(index):
        for chunk in streams[index]:
            frames = chunk.frames.copy()
            frames[:, row, col] = 0.0
            yield Chunk(chunk.start, frames, chunk.saturated, chunk.any_saturated)

    dark = truth["bias"].values.copy()
    dark[row, col] = 0.0
    read_noise = np.ones(manifest.detector.shape)
    read_noise[row, col] = 0.0
    with pytest.raises(centroids.WindowError,
                       match=rf"star 2 at position {manifest.positions[0].index}: pixel row {row}, col {col} "
                             "has zero noise"):
        centroids.measure_positions(stacks_of(manifest, chunks_of=zero_pixel), [p.index for p in manifest.positions],
                                    approx=manifest.star_approx, detector=manifest.detector, dark=dark,
                                    read_noise=read_noise, method=method)


REFERENCE = Path(__file__).parent / "data" / "centroids_9f68a43.npz"
REFERENCE_CASES = [(method, mode) for method in centroids.METHODS for mode in ("raw", "flat+metrology+width")]


def reference_products(module, manifest, truth, stacks):
    """Every product of :func:`measure_positions` of ``module`` (today's, or the one at a revision) on the noisy
    stars, for both methods, without and with every correction: {"method:mode:field": array}."""
    variance_x, variance_y = measurable_variances(truth)
    out = {}
    for method, mode in REFERENCE_CASES:
        corrected = mode != "raw"
        result = module.measure_positions(
            stacks, [p.index for p in manifest.positions], approx=manifest.star_approx, detector=manifest.detector,
            dark=truth["bias"].values, read_noise=truth["read_noise"].values,
            prnu=truth["sensitivity"].values if corrected else None, dx=truth["dx"].values if corrected else None,
            dy=truth["dy"].values if corrected else None, variance_x=variance_x if corrected else None,
            variance_y=variance_y if corrected else None, method=method)
        for field in ("x", "y", "precision_x", "precision_y", "limit_x", "limit_y"):
            out[f"{method}:{mode}:{field}"] = getattr(result, field)
    return out


def test_products_are_those_of_the_code_before_its_speed_up_within_1e_3_of_the_bound(noisy_stars):
    """The windows located together (batched FFTs, Newton and Levenberg-Marquardt iterations) give what the code
    at 9f68a43 gave, one window at a time (tests/data/centroids_9f68a43.npz, made by running this file as a
    script in a checkout of that revision), to 1e-3 of the Cramer-Rao bound: noisy stars, both methods, raw and
    corrected for flat, offsets and PRF widths."""
    manifest, truth, st = noisy_stars
    reference = np.load(REFERENCE)
    today = reference_products(centroids, manifest, truth, st)
    assert sorted(today) == sorted(reference.files)
    for key, values in today.items():
        bound = reference[key.rsplit(":", 1)[0] + f":limit_{key[-1]}"]
        assert np.isfinite(reference[key]).all()
        assert np.abs(values - reference[key]).max() < 1e-3 * bound.min(), key
    # what the tolerance allows is far below the bound, and the products are not all equal to begin with
    assert not np.array_equal(today["fourier:raw:x"], today["gaussian:raw:x"])


if __name__ == "__main__":  # the reference, with this checkout's dice_core: python tests/test_centroids.py OUT.npz
    import sys
    import tempfile

    with tempfile.TemporaryDirectory() as folder:
        manifest, truth = simulate_noisy_stars(Path(folder), prf_width_spread=0.01)
        np.savez(sys.argv[1], **reference_products(centroids, manifest, truth, stacks_of(manifest, n_batches=4)))
