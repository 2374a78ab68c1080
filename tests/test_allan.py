"""Allan deviations: against allantools, against the photon-noise limit on simulated metrology, and
their response to correlated noise."""

import allantools
import numpy as np
import pytest
import xarray as xr

from dice_core import allan, fringe_fit, fringes, simulation
from dice_core.io import Chunk, FrameStream, first_chunk, read_product
from dice_core.manifest import Detector, load_manifest


@pytest.mark.parametrize("kind", ["white", "random walk"])
def test_allan_deviation_agrees_with_allantools(rng, kind):
    series = rng.standard_normal(1000)
    if kind == "random walk":
        series = np.cumsum(series)
    for m in (1, 2, 3, 7, 50, 250, 333):  # allantools refuses a single difference (m = 500)
        ours = allan.allan_deviation(series, m)
        (_, theirs, _, _) = allantools.adev(series, rate=1.0, data_type="freq", taus=[m])
        assert ours == pytest.approx(theirs[0], rel=1e-12), m


def test_deviation_between_group_means_and_pixel_axes(rng):
    series = rng.standard_normal((101, 3))  # (sample, pixel): the last sample is left out at m = 5
    for m in (1, 5, 50):
        means = np.array([series[j * m:(j + 1) * m].mean(axis=0) for j in range(101 // m)])
        np.testing.assert_allclose(allan.group_deviation(series, m), means.std(axis=0, ddof=1), rtol=1e-13)
        np.testing.assert_allclose(allan.allan_deviation(series, m)[1],
                                   allan.allan_deviation(series[:, 1], m), rtol=1e-13)
    sizes = allan.group_sizes(101)
    assert sizes[0] == 1 and sizes[-1] == 50 and np.all(np.diff(sizes) > 0)


def test_batches_are_the_shortest_runs_covering_a_fringe_period():
    t = np.arange(3000)
    phase = 2 * np.pi * 3 * np.sin(2 * np.pi * t / 1000) ** 3  # irregular: slow near the turns
    batches = allan.fringe_batches(np.angle(np.exp(1j * phase)))  # wrapped, as the product holds it
    assert batches[0, 0] == 0 and np.all(batches[1:, 0] == batches[:-1, 1])
    lengths = batches[:, 1] - batches[:, 0]
    assert lengths.min() < lengths.max() / 3  # the sweep's speed sets them
    for start, stop in batches:
        assert np.ptp(phase[start:stop]) >= 2 * np.pi > np.ptp(phase[start:stop - 1])
    with pytest.raises(allan.AllanError, match="at least two are needed"):
        allan.fringe_batches(phase[:int(batches[1, 1]) - 1])


def test_block_weights_average_whole_blocks_of_good_pixels():
    rows, cols = np.divmod(np.arange(25 * 23), 23)
    good = np.ones(rows.size, bool)
    good[0] = False
    weights = allan.block_weights(rows, cols, good=good, block=10)
    assert weights.shape == (rows.size, 4)  # 2 x 2 whole blocks; the partial ones are left out
    assert weights.nnz == 99 + 3 * 100  # sparse: one weight a good pixel of a whole block, nothing else stored
    dense = weights.toarray()
    np.testing.assert_allclose(dense.sum(axis=0), 1)
    assert dense[0].sum() == 0 and np.count_nonzero(dense[:, 0]) == 99
    maps = np.random.default_rng(1).standard_normal((3, rows.size))
    np.testing.assert_allclose(maps @ weights, maps @ dense, rtol=1e-14)  # block means, an ndarray
    np.testing.assert_array_equal((weights**2).toarray(), dense**2)  # elementwise: the block variances' weights


def simulate_and_fit(tmp_path, **metrology):
    cfg = simulation.SimulationConfig.from_dict({
        "name": "allan-test", "frames_per_file": 100000,
        "detector": {"shape": [80, 84], "science_rows": [2, 79], "science_cols": [10, 83]},
        "dark": {"frames": 2}, "flats": {"frames": 2}, "stars": {"positions": 1, "frames": 1},
        "metrology": {"frames": 6000, "baselines": {"H1H4": {"period": 2.4, "angle_deg": 2.0}}, "pairs": {},
                      **metrology}})
    manifest = load_manifest(simulation.simulate_dataset(cfg, tmp_path))
    truth = read_product(tmp_path / "truth.nc")
    stream = FrameStream(manifest.baselines["H1H4"], manifest.detector, dtype="float32")
    solution = fringe_fit.fit_baseline(stream, truth["bias"].values, detector=manifest.detector,
                                       flat=truth["sensitivity"].values, read_noise=truth["read_noise"].values)
    dark = xr.Dataset({"dark": (("row", "col"), truth["bias"].values),
                       "noise": (("row", "col"), truth["read_noise"].values)})
    metrology_product = fringes.solution_dataset(solution, manifest.detector)
    product = allan.allan_of_baseline(stream, metrology_product, dark=dark, detector=manifest.detector)
    return product, manifest, metrology_product


@pytest.fixture(scope="module")
def photon_limited(tmp_path_factory):
    """The default preset's metrology noise (photon, read, laser intensity, amplitude, phase jitter)."""
    return simulate_and_fit(tmp_path_factory.mktemp("allan"))


def test_simulated_offsets_average_down_at_the_photon_limit(photon_limited):
    ds, _, _ = photon_limited
    assert ds.sizes["batch"] >= 30
    last = ds.isel(n_frames=-1)
    assert float(last["deviation_mean"]) == pytest.approx(float(last["photon_limit_pixel"]), rel=0.2)
    assert float(last["deviation_block_mean"]) == pytest.approx(float(last["photon_limit_block"]), rel=0.2)
    # over every group size, each curve follows its own limit
    np.testing.assert_allclose(ds["deviation_mean"], ds["photon_limit_pixel"], rtol=0.1)
    np.testing.assert_allclose(ds["deviation_mean_batch_means"], ds["photon_limit_pixel_batch_means"], rtol=0.1)
    # groups as means of batch fits: white, like white noise of the same single-batch scatter
    assert float(ds["slope_batch_means"]) == pytest.approx(-0.5, abs=0.05)
    np.testing.assert_allclose(ds["deviation_mean_batch_means"], ds["white_deviation_mean"], rtol=0.1)
    # the classical Allan deviation tells the same story for white noise
    np.testing.assert_allclose(ds["allan_deviation_mean"], ds["deviation_mean"], rtol=0.1)
    # blocks of 100 pixels: 10x lower
    ratio = ds["deviation_mean"].values / ds["deviation_block_mean"].values
    assert np.all((ratio > 7) & (ratio < 14))


def test_groups_fitted_as_a_whole_reach_the_global_fits_floor(photon_limited):
    """A group's own least-squares fit (its batches' normal equations summed) samples the phase evenly once
    it spans a few periods: from 4 batches on, the deviation is the global solution's floor scaled to the
    group's frames, sqrt(N_total / N), where the mean of one-period batch fits stays 1.2-1.35x above it."""
    ds, _, metrology = photon_limited
    scaled = float(metrology["photon_noise_floor_rms"]) * np.sqrt(metrology.sizes["frame"] / ds["n_frames"].values)
    large = ds["group_size"].values >= 4
    np.testing.assert_allclose(ds["deviation_mean"].values[large], scaled[large], rtol=0.1)
    assert float(ds["deviation_mean"][-1]) == pytest.approx(scaled[-1], rel=0.1)
    over = ds["deviation_mean_batch_means"].values[large] / ds["deviation_mean"].values[large]
    assert np.all((over > 1.2) & (over < 1.35))
    assert float(ds["deviation_mean"][0]) == pytest.approx(float(ds["deviation_mean_batch_means"][0]), rel=1e-6)


def test_a_group_fitted_as_a_whole_is_the_fit_of_its_merged_frames(photon_limited):
    """group_fits from the batches' stored sums equals batch_offsets run with each group as one batch,
    and the slope of the joint curve over groups of 4 batches or more is white noise's."""
    ds, manifest, metrology = photon_limited
    assert float(ds["slope"]) == pytest.approx(-0.5, abs=0.05)
    offsets_map = metrology["projected_offset"].values
    rows, cols = np.nonzero(np.isfinite(offsets_map))
    k = np.array([float(metrology["kx"]), float(metrology["ky"])])
    phase = metrology["pixel_phase"].values[rows, cols]
    level, amplitude, fringe_phase = (metrology[v].values for v in ("level", "amplitude", "phase"))
    factors = np.column_stack([level, amplitude * np.cos(fringe_phase), amplitude * np.sin(fringe_phase)])
    batches = allan.fringe_batches(fringe_phase)
    stream = FrameStream(manifest.baselines["H1H4"], manifest.detector, dtype="float32")
    dark = np.zeros(manifest.detector.shape)
    offsets, sums = allan.batch_offsets(stream, batches, factors, dark, phase, k, rows, cols, return_sums=True)
    good = np.isfinite(offsets).all(axis=0)
    pixel_factors = np.column_stack([np.ones(rows.size), np.sin(phase), np.cos(phase)])
    weights = allan.block_weights(rows, cols, good=good)
    m = 3
    groups = allan.group_fits(sums, batches, factors, phase, k, rows, cols, [m], pixel_factors=pixel_factors,
                              gain=10.0, read_noise=np.full(rows.size, 4.0), good=good, weights=weights)
    merged = np.array([(batches[g * m, 0], batches[(g + 1) * m - 1, 1]) for g in range(len(batches) // m)])
    direct = allan.batch_offsets(stream, merged, factors, dark, phase, k, rows, cols)
    # to the float32 rounding of the stored sums: 2e-8 pixel, 1e-3 of the deviation (1.7e-4 pixel)
    np.testing.assert_allclose(groups["deviation"][0], direct.std(axis=0, ddof=1), rtol=0, atol=1e-7)


def test_the_papers_formula_is_optimistic_for_one_period_batches(photon_limited):
    """sqrt(N/2) assumes every phase equally sampled; a one-period batch of an exponential sweep
    samples some phases sparsely, and its fit does worse (documented in docs/metrology.md)."""
    ds, _, metrology = photon_limited
    ratio = ds["photon_limit_pixel_batch_means"].values / ds["photon_limit_pixel_paper"].values
    assert np.all((ratio > 1.1) & (ratio < 1.6))
    # the paper's formula itself is right for the whole acquisition: it matches the global fit's floor
    whole = allan.photon_limit(np.array([metrology.sizes["frame"]]), float(metrology["level"].mean()),
                               amplitude=float(metrology["amplitude"].mean()), iota=1.0, alpha=1.0, gain=10.0,
                               read_noise=4.0, k_norm=float(np.hypot(metrology["kx"], metrology["ky"])))
    assert float(whole[0, 0]) == pytest.approx(float(metrology["photon_noise_floor_rms"]), rel=0.1)


def test_common_mode_random_walks_are_absorbed_by_the_frame_fit(tmp_path):
    """A random walk of the fringe phase or of the laser intensity is common to all pixels: the
    per-frame phase and level of the global solution follow it, and the offsets do not see it."""
    ds, _, _ = simulate_and_fit(tmp_path, phase_random_walk=0.02, intensity_random_walk=2e-3)
    assert float(ds["slope_batch_means"]) == pytest.approx(-0.5, abs=0.05)
    last = ds.isel(n_frames=-1)
    assert float(last["deviation_mean"]) == pytest.approx(float(last["photon_limit_pixel"]), rel=0.2)


def test_stray_light_with_a_drifting_path_shows_as_correlated_noise(tmp_path):
    """A parasitic fringe (1% of the fringe amplitude) whose extra path random-walks moves each
    pixel's apparent phase differently: the deviation stops falling as N^-1/2."""
    ds, _, _ = simulate_and_fit(tmp_path, stray_light=0.01, stray_light_phase_walk=0.01)
    assert float(ds["slope"]) > -0.4
    last = ds.isel(n_frames=-1)
    assert float(last["deviation_mean"]) > 2 * float(last["photon_limit_pixel"])
    assert float(last["deviation_mean_batch_means"]) > 2 * float(last["white_deviation_mean"])


def test_too_few_frames_for_two_batches(photon_limited, tmp_path):
    ds, manifest, metrology = photon_limited
    short = metrology.isel(frame=slice(0, int(ds["batch_frames"][0]) + 10))
    with pytest.raises(allan.AllanError, match="at least two are needed"):
        allan.fringe_batches(short["phase"].values)
    stream = FrameStream(manifest.baselines["H1H4"], manifest.detector, dtype="float32")
    with pytest.raises(allan.AllanError, match="6000 frames, its solution"):
        allan.allan_of_baseline(stream, short, dark=xr.Dataset(), detector=manifest.detector)


def synthetic_fringes(rng, *, n_frames=1200, shape=(12, 14), k=(2.6, 0.15), noise=1.0):
    """Chunks of fringes I = B + A sin(theta_p + phi(t)) + noise, with their frame factors and pixel phases."""
    rows, cols = (a.ravel() for a in np.indices(shape))
    theta = k[0] * cols + k[1] * rows
    phi = 2 * np.pi * np.arange(n_frames) / 97.0
    level, amplitude = 1000.0, 600.0
    frames = level + amplitude * np.sin(theta[None, :] + phi[:, None]) + noise * rng.standard_normal((n_frames,
                                                                                                      theta.size))
    frames = frames.reshape(n_frames, *shape)
    chunks = [Chunk(start, frames[start:start + 100], np.zeros((min(100, n_frames - start), *shape), bool), False)
              for start in range(0, n_frames, 100)]
    factors = np.column_stack([np.full(n_frames, level), amplitude * np.cos(phi), amplitude * np.sin(phi)])
    return chunks, factors, phi, theta, rows, cols


@pytest.mark.parametrize("constant", [np.pi - 1e-3, np.pi + 1e-3, -np.pi + 2e-4, 0.4])
def test_batch_offsets_ignore_the_constant_phase_the_gauge_leaves_free(rng, constant):
    """The reference phases may differ from the batches' by any constant, near pi included (issue 10)."""
    chunks, factors, phi, theta, rows, cols = synthetic_fringes(rng)
    batches = allan.fringe_batches(phi)
    k = (2.6, 0.15)
    pattern = 2e-3 * np.where((rows + cols) % 2 == 0, 1.0, -1.0)  # rad: offsets the batches must show
    reference_phase = theta + constant + pattern
    offsets = allan.batch_offsets(chunks, batches, factors, np.zeros((12, 14)), reference_phase, k, rows, cols)
    design = np.column_stack([np.ones(rows.size), cols, rows])
    expected = -(pattern - design @ np.linalg.lstsq(design, pattern, rcond=None)[0]) / np.hypot(*k)
    # noise: 1 adu on 600 adu of fringe over ~100 frames, about 1.4e-4 rad, 5e-5 pixel
    assert np.max(np.abs(offsets - expected)) < 5e-4
    assert np.sqrt(np.mean((offsets - expected) ** 2)) < 1e-4


def test_allan_is_the_same_bit_for_bit_whatever_the_workers(tmp_path):
    """Fixed lanes of whole files, summed in order; a batch cut between two lanes sums their parts."""
    cfg = simulation.SimulationConfig.from_dict({
        "name": "allan-lanes", "frames_per_file": 450,
        "detector": {"shape": [40, 44], "science_rows": [2, 39], "science_cols": [3, 43]},
        "dark": {"frames": 2}, "flats": {"frames": 2},
        "stars": {"positions": 1, "frames": 1, "pattern_centre": [23.0, 20.0], "pattern_side": 16.0},
        "metrology": {"frames": 1800, "sweep_frames": 300,
                      "baselines": {"H1H4": {"period": 2.4, "angle_deg": 2.0}}, "pairs": {}}})
    manifest = load_manifest(simulation.simulate_dataset(cfg, tmp_path))
    truth = read_product(tmp_path / "truth.nc")
    stream = FrameStream(manifest.baselines["H1H4"], manifest.detector, dtype="float32")
    assert len(stream.split(2)) == 2
    solution = fringe_fit.fit_baseline(stream, truth["bias"].values, detector=manifest.detector,
                                       flat=truth["sensitivity"].values, read_noise=truth["read_noise"].values)
    metrology = fringes.solution_dataset(solution, manifest.detector)
    dark = xr.Dataset({"dark": (("row", "col"), truth["bias"].values),
                       "noise": (("row", "col"), truth["read_noise"].values)})
    one, two = (allan.allan_of_baseline(stream, metrology, dark=dark, detector=manifest.detector, workers=n)
                for n in (1, 2))
    xr.testing.assert_identical(one, two)
    # lanes are a summation order, not a different estimate: the same batch fits from one list of chunks
    phase = metrology["phase"].values
    rows, cols = np.nonzero(np.isfinite(metrology["projected_offset"].values))
    k = np.array([float(metrology["kx"]), float(metrology["ky"])])
    reference_phase = k[0] * cols + k[1] * rows + np.hypot(*k) * metrology["projected_offset"].values[rows, cols]
    factors = np.column_stack([metrology["level"].values, metrology["amplitude"].values * np.cos(phase),
                               metrology["amplitude"].values * np.sin(phase)])
    batches = allan.fringe_batches(phase)
    assert any(start < 900 < stop for start, stop in batches)  # a batch cut between the two lanes
    reference = first_chunk(stream).frames.mean(axis=0)  # as allan_of_baseline centres the float32 frames
    whole = allan.batch_offsets(list(stream.centred(reference)), batches, factors, truth["bias"].values,
                                reference_phase, k, rows, cols, reference=reference)
    np.testing.assert_allclose(one["batch_offset"].values[:, rows, cols], whole, rtol=0, atol=1e-8)


def allan_inputs(rng, n_batches=8, frames=100, side=20):
    """Synthetic batch offsets on a side x side detector, one pixel without offsets."""
    detector = Detector(shape=(side, side), science_rows=(0, side), science_cols=(0, side), gain=2.5,
                        saturation=6e4)
    rows, cols = np.divmod(np.arange(side * side), side)
    offsets = 1e-3 * rng.standard_normal((n_batches, rows.size))
    offsets[:, 7] = np.nan
    batches = np.column_stack([np.arange(n_batches) * frames, np.arange(1, n_batches + 1) * frames])
    iota, alpha = rng.uniform(0.8, 1.2, rows.size), rng.uniform(0.5, 0.9, rows.size)
    read_noise = rng.uniform(3, 5, rows.size)
    keywords = dict(level=2000.0, amplitude=800.0, iota=iota, alpha=alpha, read_noise=read_noise, k=(1.2, 0.3),
                    block=10)
    return (offsets, np.full(offsets.shape, 1e-3), batches, rows, cols, detector), keywords


def test_first_frame_limit_is_the_papers_formula_on_the_measured_noise(rng):
    """photon_limit_pixel_first_frame: sqrt(f/g + sr^2) / (A alpha |K| sqrt(N/2)), rms over the pixels with
    offsets, f the first frame minus the dark (a negative f counts as 0); first_frame_noise: the rms of
    sqrt(f/g + sr^2)."""
    args, keywords = allan_inputs(rng)
    rows = args[3]
    first = rng.uniform(500, 3000, rows.size)
    first[3] = -20.0
    ds = allan.allan_dataset(*args, **keywords, first_frame=first)
    good = np.arange(rows.size) != 7
    noise = np.sqrt(np.maximum(first, 0) / 2.5 + keywords["read_noise"] ** 2)[good]
    per_frame = noise / (800.0 * keywords["alpha"][good] * np.hypot(1.2, 0.3))
    n = ds["n_frames"].values
    np.testing.assert_allclose(n, ds["group_size"].values * 100)
    expected = np.sqrt(np.mean(per_frame**2)) / np.sqrt(n / 2)
    np.testing.assert_allclose(ds["photon_limit_pixel_first_frame"].values, expected, rtol=1e-12)
    assert float(ds["first_frame_noise"]) == pytest.approx(np.sqrt(np.mean(noise**2)), rel=1e-12)
    assert ds["photon_limit_pixel_first_frame"].attrs["units"] == "pixel"
    assert ds["first_frame_noise"].attrs["units"] == "adu"
    # single-batch deviation, scaled by 1/sqrt(batches per group) along the curve
    np.testing.assert_allclose(ds["photon_limit_pixel_first_frame"].values,
                               expected[0] / np.sqrt(ds["group_size"].values), rtol=1e-12)
    # a first frame at the model's level B iota gives the paper's theoretical limit
    model = allan.allan_dataset(*args, **keywords, first_frame=2000.0 * keywords["iota"])
    np.testing.assert_allclose(model["photon_limit_pixel_first_frame"], model["photon_limit_pixel_paper"],
                               rtol=1e-12)
    # without a first frame, the product is as before
    plain = allan.allan_dataset(*args, **keywords)
    assert "photon_limit_pixel_first_frame" not in plain and "first_frame_noise" not in plain
    xr.testing.assert_identical(plain, ds.drop_vars(["photon_limit_pixel_first_frame", "first_frame_noise"]))


def test_the_product_is_the_statistics_with_their_metadata(rng):
    """allan_statistics computes plain arrays, without a detector; allan_dataset only places them on the
    detector's (row, col) maps and adds units and long names to every variable."""
    (offsets, floors, batches, rows, cols, detector), keywords = allan_inputs(rng)
    statistics = allan.allan_statistics(offsets, floors, batches, rows, cols, gain=detector.gain, **keywords)
    ds = allan.allan_dataset(offsets, floors, batches, rows, cols, detector, **keywords)
    for name in ds.data_vars:
        values = np.asarray(getattr(statistics, name))
        if "row" in ds[name].dims:  # pixel arrays (…, pixel) as maps, NaN off the pixels
            np.testing.assert_array_equal(ds[name].values[:, rows, cols], values.astype(ds[name].dtype))
        else:
            np.testing.assert_array_equal(ds[name].values, values)
        assert ds[name].attrs["units"] and ds[name].attrs["long_name"]
    np.testing.assert_array_equal(ds["n_frames"].values, statistics.n_frames)
    assert ds.attrs == {"frames_per_batch": statistics.frames_per_batch, "block_size": 10}
    # the optional statistics are absent from the product when not computed
    assert statistics.deviation_mean_batch_means is None and "deviation_mean_batch_means" not in ds
    assert statistics.first_frame_noise is None and "first_frame_noise" not in ds
