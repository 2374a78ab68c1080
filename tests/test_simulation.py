"""The simulated testbed: format, determinism, statistics of each acquisition, and the star geometry."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from dice_core import simulation
from dice_core.io import FrameStream, read_product
from dice_core.manifest import load_manifest

from conftest import small_config


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    cfg = small_config(frames_per_file=120)
    path = simulation.simulate_dataset(cfg, tmp_path_factory.mktemp("sim") / "raw")
    return cfg, load_manifest(path), read_product(path.parent / "truth.nc")


def test_writes_the_raw_format_and_truth_contract(dataset):
    cfg, manifest, truth = dataset
    assert manifest.name == cfg.name
    assert set(manifest.baselines) == {"H1H4", "V1V4", "H2H4", "V2V4"}
    assert len(manifest.baselines["H1H4"].files) == 2  # 200 frames at 120 per file
    for name, units in {"dx": "pixel", "dy": "pixel", "sensitivity": "1", "kx": "rad/pixel", "ky": "rad/pixel",
                        "phase": "rad", "star_x": "pixel", "star_y": "pixel"}.items():
        assert truth[name].attrs["units"] == units, name
    assert truth["dx"].dims == ("row", "col") and truth["phase"].dims == ("baseline", "frame")
    assert truth["star_x"].dims == ("position", "star") and truth.sizes["star"] == 5
    for acquisition in [manifest.dark, *manifest.flats.values(), *manifest.baselines.values()]:
        stream = FrameStream(acquisition, manifest.detector)
        assert stream.n_frames == {"dark": 100, "flat": 100, "baseline": 200}[acquisition.label.split()[0]]


def test_truth_follows_the_configuration(dataset):
    cfg, manifest, truth = dataset
    sl = manifest.detector.science_slices
    sens = truth["sensitivity"].values[sl]
    assert sens.mean() == pytest.approx(1.0, abs=1e-12)
    assert 1.5e-3 < np.median(np.abs(sens - np.median(sens))) * 1.4826 < 3e-3  # robust rms, dust excluded
    assert sens.min() < 1 - 0.01  # dust pixels
    for d in ("dx", "dy"):
        values = truth[d].values[sl]
        assert np.std(values) == pytest.approx(1e-3, rel=0.1)
        # offsets are defined up to an affine map: the truth has none
        rows, cols = np.indices(values.shape)
        assert abs(values.mean()) < 1e-15 and abs(np.corrcoef(values.ravel(), cols.ravel())[0, 1]) < 1e-10
    width = truth["prf_sigma_x"].values[sl]
    assert np.std(width) / np.mean(width) == pytest.approx(0.01, rel=0.15)
    period = np.hypot(truth["kx"], truth["ky"]).values
    np.testing.assert_allclose(2 * np.pi / period, [2.4, 2.4, 4.0, 4.0])


def test_deterministic(dataset, tmp_path):
    cfg, manifest, truth = dataset
    path = simulation.simulate_dataset(cfg, tmp_path / "again")
    again = load_manifest(path)
    xr.testing.assert_equal(truth, read_product(path.parent / "truth.nc"))  # values; attrs hold timestamps
    for a, b in zip(manifest.all_files(), again.all_files()):
        assert a.read_bytes() == b.read_bytes(), a.name


def test_frames_do_not_depend_on_chunk_size(dataset):
    import dataclasses

    cfg, _, truth = dataset
    small = dataclasses.replace(cfg, chunk_frames=7)
    for kind, name in [("baseline", "V1V4"), ("flat", "fiber_b"), ("dark", "dark"), ("position", 1)]:
        a = np.concatenate(list(simulation.acquisition_chunks(cfg, truth, kind=kind, name=name, start=0, stop=50)))
        b = np.concatenate(list(simulation.acquisition_chunks(small, truth, kind=kind, name=name, start=0, stop=50)))
        np.testing.assert_array_equal(a, b)


def test_a_large_detector_is_simulated_in_chunks_of_few_frames(dataset, monkeypatch):
    import dataclasses

    cfg, _, truth = dataset
    pixels = cfg.detector.shape[0] * cfg.detector.shape[1]
    large = dataclasses.replace(cfg, detector=dataclasses.replace(cfg.detector, shape=(1024, 1024)))
    assert simulation.simulation_chunk_frames(cfg) == simulation.SIMULATION_CHUNK_SAMPLES // pixels < cfg.chunk_frames
    for preset, frames in (("ci", 148), ("default", 39), ("paper", 39)):  # 2 MiB of float64 a temporary
        path = Path(__file__).parents[1] / "config" / "presets" / f"{preset}.yaml"
        assert simulation.simulation_chunk_frames(simulation.load_preset(path)) == frames
    assert simulation.simulation_chunk_frames(large) == 1  # 1024 x 1024 float64 = 8 MiB a temporary
    whole = np.concatenate(list(simulation.acquisition_chunks(cfg, truth, kind="baseline", name="H1H4", start=0,
                                                              stop=20)))
    monkeypatch.setattr(simulation, "SIMULATION_CHUNK_SAMPLES", 3 * pixels + 1)
    chunks = list(simulation.acquisition_chunks(cfg, truth, kind="baseline", name="H1H4", start=0, stop=20))
    assert [len(c) for c in chunks] == [3, 3, 3, 3, 3, 3, 2]
    np.testing.assert_array_equal(np.concatenate(chunks), whole)


@pytest.mark.parametrize("threshold", [1000.0, None])
@pytest.mark.parametrize("level", [3.0, 40.0, 8000.0])  # adu: 30 and 400 e- are Poisson, 8e4 e- normal
def test_photon_and_read_noise_have_the_poisson_mean_and_variance(level, threshold):
    cfg = small_config(detector={"gaussian_photons_above": threshold})
    gain = cfg.detector.gain
    shape = (4000, 2, 3)

    def read_out(read_noise):
        truth = xr.Dataset({"bias": (("row", "col"), np.full(shape[1:], 500.0)),
                            "read_noise": (("row", "col"), np.full(shape[1:], read_noise))})
        rngs = (np.random.default_rng(1), np.random.default_rng(2))
        return simulation._read_out(np.full(shape, level), truth, cfg, rngs, np.random.default_rng(3)) - 500.0

    samples = read_out(4.0)
    variance = level / gain + 16.0
    assert samples.mean() == pytest.approx(level, abs=4 * np.sqrt(variance / samples.size))
    assert samples.var() == pytest.approx(variance, rel=4 * np.sqrt(2 / samples.size))
    # which law: Poisson counts are whole electrons, normal draws are not
    electrons = read_out(0.0) * gain
    whole = np.allclose(electrons, np.round(electrons), rtol=0, atol=1e-6)
    assert whole == (threshold is None or level * gain < threshold)


def test_dark_is_bias_plus_read_noise(dataset):
    _, manifest, truth = dataset
    frames = np.concatenate([c.frames for c in FrameStream(manifest.dark, manifest.detector)])
    sl = manifest.detector.science_slices
    residual = frames[:, sl[0], sl[1]] - truth["bias"].values[sl]
    assert abs(residual.mean()) < 0.05
    # read noise plus the uniform quantisation of integer samples
    expected = np.sqrt(np.mean(truth["read_noise"].values[sl] ** 2) + 1 / 12)
    assert residual.std() == pytest.approx(expected, rel=0.01)


def test_metrology_frames_follow_the_fringe_model(dataset):
    cfg, manifest, truth = dataset
    frames = np.concatenate([c.frames for c in FrameStream(manifest.baselines["H2H4"], manifest.detector)])
    b = truth.sel(baseline="H2H4")
    prf = simulation.pixel_response(truth)
    envelope, visibility = truth["envelope"].values, truth["visibility"].values
    response = prf.fringe_response(float(b.kx), float(b.ky)) * envelope * visibility
    phase = b["phase"].values[:, None, None]
    model = (b["fringe_level"].values[:, None, None] * prf.sensitivity * envelope
             + b["fringe_amplitude"].values[:, None, None] * np.imag(response * np.exp(1j * phase))
             + truth["bias"].values)
    residual = (frames - model)[:, 2:39, 3:43]
    # what is left is photon noise (gain 10 e-/adu) plus read noise
    expected = np.sqrt((model - truth["bias"].values)[:, 2:39, 3:43] / cfg.detector.gain
                       + truth["read_noise"].values[2:39, 3:43] ** 2 + 1 / 12)
    assert np.std(residual / expected) == pytest.approx(1.0, abs=0.02)
    assert abs(np.mean(residual / expected)) < 0.02
    # the phase sweeps back and forth over several 2 pi
    assert np.ptp(b["phase"].values) > 2 * 2 * np.pi


def test_laser_noise_scales_level_and_amplitude_together(dataset):
    _, _, truth = dataset
    b = truth.sel(baseline="H1H4")
    level = b["fringe_level"].values / 10000 - 1
    amplitude = b["fringe_amplitude"].values / 6000 - 1
    assert np.std(level) == pytest.approx(1e-2, rel=0.2)
    assert np.corrcoef(level, amplitude)[0, 1] > 0.99
    assert np.std(amplitude - level) == pytest.approx(1e-3, rel=0.3)


def test_star_images_centre_on_the_truth(dataset):
    _, manifest, truth = dataset
    position = manifest.positions[1]
    frames = np.concatenate([c.frames for c in FrameStream(position.acquisition, manifest.detector)])
    image = frames.mean(axis=0) - truth["bias"].values
    for star in range(5):
        x, y = float(truth.star_x[1, star]), float(truth.star_y[1, star])
        r, c = int(round(y)), int(round(x))
        window = image[r - 4:r + 5, c - 4:c + 5] - 10.0  # background
        rows, cols = np.indices(window.shape)
        assert (window * cols).sum() / window.sum() + c - 4 == pytest.approx(x, abs=0.02)
        assert (window * rows).sum() / window.sum() + r - 4 == pytest.approx(y, abs=0.02)


def geometry_config(**stars):
    return small_config(detector={"shape": [80, 84], "science_rows": [2, 79], "science_cols": [10, 83]},
                        stars={"pattern_centre": [46.0, 40.0], "pattern_side": 40.0, **stars})


def test_reference_pose_projects_the_nominal_pattern():
    cfg = geometry_config()
    pattern = np.array([[46.0, 40.0], [26.0, 20.0], [66.0, 20.0], [26.0, 60.0], [66.0, 60.0]])
    projected = simulation.project_stars(pattern, np.zeros((1, 6)), cfg=cfg)[0]
    np.testing.assert_allclose(projected, pattern, atol=1e-9)


def test_translation_moves_all_stars_together():
    cfg = geometry_config()
    pattern = np.array([[46.0, 40.0], [26.0, 20.0], [66.0, 60.0]])
    moved = simulation.project_stars(pattern, np.array([[0.3, -0.2, 0, 0, 0, 0]]), cfg=cfg)[0]
    np.testing.assert_allclose(moved - pattern, [[-0.3, 0.2]] * 3, atol=1e-9)


def test_tilt_gives_the_non_homogeneous_scale_of_appendix_d():
    """A tip theta changes the top and bottom star separations by -+alpha*theta (relative), on axis."""
    cfg = geometry_config(off_axis_deg=0.0)
    theta, side, distance = 1e-3, 40.0, 25000.0
    rows, cols = 80, 84
    xc, yc = (cols - 1) / 2, (rows - 1) / 2  # on the detector's centre column
    pattern = np.array([[xc, yc], [xc, yc - side / 2], [xc, yc + side / 2]])
    tipped = simulation.project_stars(pattern, np.array([[0, 0, 0, theta, 0, 0]]), cfg=cfg)[0]
    s_low, s_high = tipped[0, 1] - tipped[1, 1], tipped[2, 1] - tipped[0, 1]
    alpha = (side / 2) / distance
    # first order: the two half-separations differ by 2*alpha*theta relative (paper's appendix D)
    assert (s_high - s_low) / (side / 2) == pytest.approx(2 * alpha * theta, rel=0.02)


def test_unknown_config_keys_are_refused():
    with pytest.raises(ValueError, match="unknown key"):
        simulation.SimulationConfig.from_dict({"detector": {"gian": 10}})
    with pytest.raises(ValueError, match="unknown baseline"):
        simulation.SimulationConfig.from_dict({"metrology": {"pairs": {"P": ["H1H4", "X"]}}})
    with pytest.raises(ValueError, match="science area"):
        simulation.SimulationConfig.from_dict({"detector": {"science_rows": [0, 200]}})


@pytest.mark.parametrize("preset", ["default", "ci", "paper", "large", "chromatic"])
def test_presets_load_and_lay_out_a_valid_manifest(preset, tmp_path):
    from dice_core.manifest import parse_manifest

    cfg = simulation.load_preset(Path(__file__).parents[1] / "config" / "presets" / f"{preset}.yaml")
    manifest = parse_manifest(simulation.dataset_layout(cfg), tmp_path / "dataset.yaml")
    assert manifest.name == f"sim-{preset}"
    assert len(simulation.file_jobs(cfg)) == len(manifest.all_files())
    # the stars stay inside the science area at every position, with room for a window
    truth_poses = simulation._nominal_poses(cfg.stars)
    stars = simulation.project_stars(simulation._nominal_pattern(cfg.stars), truth_poses, cfg=cfg)
    assert stars[..., 1].min() > cfg.detector.science_rows[0] + 5
    assert stars[..., 1].max() < cfg.detector.science_rows[1] - 5


def test_the_two_source_phase_and_its_gradient(rng):
    tip_a, tip_b = np.array([0.008, 0.001, 0.6]), np.array([0.0146, 0.0012, 0.6])
    x, y = rng.uniform(0, 84, 20), rng.uniform(0, 80, 20)
    phi, kx, ky = simulation.two_source_phase(x, y, tip_a, tip_b, wavelength=633e-9, pixel_pitch=24e-6)
    r = np.stack([x * 24e-6, y * 24e-6, 0 * x], -1)
    np.testing.assert_allclose(phi, 2 * np.pi / 633e-9 * (np.linalg.norm(r - tip_a, axis=-1)
                                                           - np.linalg.norm(r - tip_b, axis=-1)), rtol=1e-12)
    h = 1e-3
    for grad, dx, dy in ((kx, h, 0), (ky, 0, h)):
        ahead, _, _ = simulation.two_source_phase(x + dx, y + dy, tip_a, tip_b, wavelength=633e-9, pixel_pitch=24e-6)
        behind, _, _ = simulation.two_source_phase(x - dx, y - dy, tip_a, tip_b, wavelength=633e-9,
                                                   pixel_pitch=24e-6)
        np.testing.assert_allclose(grad, (ahead - behind) / (2 * h), rtol=0, atol=1e-6)
    # from a to b: about 2 pi (b - a) / (wavelength distance), per pixel
    assert kx.mean() == pytest.approx(2 * np.pi * 0.0066 / (633e-9 * 0.6) * 24e-6, rel=0.01)


def test_spherical_fringes_are_those_of_two_point_sources(tmp_path):
    """Noiseless frames against the dataset format's two-source phase, integrated over each PRF by brute
    force, independently of the simulator's local-plane-wave response."""
    cfg = small_config(detector={"photon_noise": False, "read_noise": 0.0, "dtype": "float32"},
                       metrology={"spherical": True, "frames": 200, "sweep_frames": 100, "laser_rsd": 0.0,
                                  "amplitude_rsd": 0.0, "phase_jitter": 0.0,
                                  "baselines": {"H1H4": {"period": 2.4, "angle_deg": 2.0, "midpoint": [0.012, 0.0]}},
                                  "pairs": {}})
    path = simulation.simulate_dataset(cfg, tmp_path / "raw")
    manifest, truth = load_manifest(path), read_product(path.parent / "truth.nc")
    true_tips, _ = simulation.fiber_tips(cfg)
    np.testing.assert_allclose(truth["fiber_position"].values, np.array(list(true_tips.values())))
    # the manifest's tips are the bench's nominal ones, 0.5-1 mm off the true ones
    off = [np.linalg.norm(np.array(manifest.geometry.fibers[f]) - true_tips[f]) for f in true_tips]
    assert all(0.5e-3 <= d <= 1e-3 for d in off)
    # the period asked for, at the detector centre despite the obliquity; the contract's K its best plane
    _, kx, ky = simulation.two_source_phase(21.5, 19.5, *true_tips.values(), wavelength=633e-9, pixel_pitch=24e-6)
    assert 2 * np.pi / np.hypot(kx, ky) == pytest.approx(2.4, rel=1e-6)
    assert 2 * np.pi / np.hypot(float(truth["kx"][0]), float(truth["ky"][0])) == pytest.approx(2.4, rel=2e-3)
    # each pixel's response, integrated by brute force over its PRF under the exact phase
    rows, cols = np.indices(cfg.detector.shape)
    prf = simulation.pixel_response(truth)
    x0, y0 = prf.centres()
    a, b = true_tips["H1H4a"], true_tips["H1H4b"]
    nodes, weights = np.polynomial.legendre.leggauss(96)
    u, w = 0.5 * nodes, 0.5 * weights  # the PRF's support, [-0.5, 0.5] pixel
    response = np.zeros(cfg.detector.shape, complex)
    pixels = [(5, 6), (20, 22), (37, 41), (2, 40)]
    for r, c in pixels:
        kernel = np.outer(w * np.exp(-np.abs(u) ** 4 / (2 * prf.sigma_y[r, c] ** 4)),
                          w * np.exp(-np.abs(u) ** 4 / (2 * prf.sigma_x[r, c] ** 4)))
        phi, _, _ = simulation.two_source_phase(x0[r, c] + u[None, :], y0[r, c] + u[:, None], a, b,
                                                wavelength=633e-9, pixel_pitch=24e-6)
        response[r, c] = prf.sensitivity[r, c] * np.sum(kernel * np.exp(1j * phi)) / np.sum(kernel)
    response *= truth["envelope"].values * truth["visibility"].values
    frames = np.concatenate([c.frames for c in FrameStream(manifest.baselines["H1H4"], manifest.detector)])
    bl = truth.sel(baseline="H1H4")
    phase = bl["phase"].values[:, None]
    for model_response, close in ((response, True), (None, False)):
        if model_response is None:  # the best plane's plane wave: what a plane-wave model would say
            plane = prf.fringe_response(float(bl["kx"]), float(bl["ky"]))
            surface = truth["fringe_phase_surface"].values[0]
            offset = np.angle(np.mean(np.exp(1j * (surface - bl["kx"].values * x0 - bl["ky"].values * y0))))
            model_response = plane * np.exp(1j * offset) * truth["envelope"].values * truth["visibility"].values
        for r, c in pixels:
            model = (bl["fringe_level"].values * prf.sensitivity[r, c] * truth["envelope"].values[r, c]
                     + bl["fringe_amplitude"].values * np.imag(model_response[r, c] * np.exp(1j * phase[:, 0]))
                     + truth["bias"].values[r, c])
            miss = np.max(np.abs(frames[:, r, c] - model))
            assert (miss < 2e-2) if close else (miss > 1.0), (r, c, miss)


# ------------------------------------------------------------------ chromatic pixels (issue 26)

#: Digests of the presets' truth (every variable's values), of the first 40 frames of each kind of acquisition
#: (every baseline) and of the manifest, computed with the code before issue 26 (commit 450decf): the chromatic
#: simulator, off by default, must leave today's datasets as they were, bit for bit.
BEFORE_ISSUE_26 = {"ci": ("efd7bd394db3ec1f", "296c15efaf9c6b58", "bd634d34dc91f2f2"),
                   "default": ("586f99ac881785b3", "3c9c489b2ab5a55b", "ee49d94105099f6a"),
                   "paper": ("46aad7a4939c1b25", "1fe6f546f613ffd6", "3ffc0f8d2f251258")}


def digests(cfg):
    """(truth, frames, manifest) digests of a simulation, as BEFORE_ISSUE_26 holds them."""
    import hashlib
    import json

    truth = simulation.make_truth(cfg)
    values = hashlib.sha256()
    for name in sorted(truth.data_vars):
        values.update(name.encode())
        values.update(np.ascontiguousarray(truth[name].values).tobytes())
    frames, seen = hashlib.sha256(), set()
    for kind, name, start, stop in simulation.file_jobs(cfg).values():
        if kind in seen and kind != "baseline":
            continue
        seen.add(kind)
        for chunk in simulation.acquisition_chunks(cfg, truth, kind=kind, name=name, start=start,
                                                   stop=min(stop, start + 40)):
            frames.update(np.ascontiguousarray(chunk, dtype=np.float64).tobytes())
    layout = hashlib.sha256(json.dumps(simulation.dataset_layout(cfg), sort_keys=True).encode())
    return values.hexdigest()[:16], frames.hexdigest()[:16], layout.hexdigest()[:16]


@pytest.mark.parametrize("preset", sorted(BEFORE_ISSUE_26))
def test_today_s_presets_are_simulated_bit_for_bit_as_before_the_chromatic_simulator(preset):
    cfg = simulation.load_preset(Path(__file__).parents[1] / "config" / "presets" / f"{preset}.yaml")
    assert not simulation.is_chromatic(cfg)
    assert digests(cfg) == BEFORE_ISSUE_26[preset]


def chromatic_config(**chromatic):
    """A small chromatic bench: noiseless float frames, lasers at 633 and 450 nm (one pair each), a laser flat
    at 450 nm, warm broadband stars."""
    return small_config(detector={"photon_noise": False, "read_noise": 0.0, "dtype": "float32"},
                        metrology={"wavelengths": [633e-9, 450e-9], "spherical": True,
                                   "baselines": {"H1H4": {"period": 2.4, "angle_deg": 2.0, "midpoint": [0.01, 0.0]},
                                                 "V1V4": {"period": 2.4, "angle_deg": 93.0}},
                                   "pairs": {"P14": ["H1H4", "V1V4"]}},
                        flats={"wavelengths": [450e-9]}, stars={"spectrum": "warm"},
                        chromatic={"amplitude": 3.0, **chromatic})


def test_a_chromatic_bench_writes_format_1_2_and_the_response_at_each_wavelength(tmp_path):
    from dice_core.chromatic import named_spectrum
    from dice_core.manifest import parse_manifest

    cfg = chromatic_config()
    manifest = parse_manifest(simulation.dataset_layout(cfg), tmp_path / "dataset.yaml")
    assert list(manifest.pairs) == ["P14", "P14_450"] and manifest.wavelengths == (633e-9, 450e-9)
    assert manifest.pairs["P14_450"] == ("H1H4_450", "V1V4_450") and manifest.flats_at(450e-9) == ["laser_450"]
    assert manifest.flats["fiber_a"].wavelength is None
    wavelength, weight = named_spectrum("warm")
    np.testing.assert_allclose(manifest.spectrum.wavelength, wavelength)
    np.testing.assert_allclose(manifest.spectrum.weight, weight, rtol=1e-5)
    # each laser's fiber tips give the configured period at its own wavelength
    assert set(manifest.geometry.baseline_fibers) == {"H1H4", "V1V4", "H1H4_450", "V1V4_450"}
    truth = simulation.make_truth(cfg)
    np.testing.assert_allclose(2 * np.pi / np.hypot(truth["kx"], truth["ky"]).values, 2.4, rtol=0.02)
    assert 450e-9 in truth["wavelength"].values and 633e-9 in truth["wavelength"].values
    for name in ("dx", "dy", "sensitivity", "width_x", "width_y"):
        assert truth[f"{name}_wavelength"].dims == ("wavelength", "row", "col")
        # the contract's variables are the response at metrology.wavelength
        np.testing.assert_array_equal(truth[f"{name}_wavelength"].sel(wavelength=633e-9).values, truth[name].values)
    sl = manifest.detector.science_slices
    change = (truth["dx_wavelength"].sel(wavelength=400e-9) - truth["dx"]).values[sl]
    assert np.std(change) == pytest.approx(3.0 * 1e-3, rel=0.1)  # the configured change to 400 nm


def test_each_acquisition_sees_the_detector_at_its_own_wavelength():
    cfg = chromatic_config()
    truth = simulation.make_truth(cfg)
    bias, sl = truth["bias"].values, (slice(2, 39), slice(3, 43))

    def mean_frame(kind, name):
        frames = np.concatenate(list(simulation.acquisition_chunks(cfg, truth, kind=kind, name=name, start=0,
                                                                   stop=4)))
        return frames.mean(axis=0) - bias

    at = {w: simulation.pixel_response(truth, w) for w in (450e-9, 633e-9)}
    # the laser flat follows the sensitivity at 450 nm, the white one the lamp's spectrum-weighted sensitivity
    laser = mean_frame("flat", "laser_450") / truth["flat_illumination"].sel(flat="laser_450").values
    white = mean_frame("flat", "fiber_a") / truth["flat_illumination"].sel(flat="fiber_a").values
    lamp = np.tensordot(truth["flat_spectrum_weight"].values, truth["sensitivity_wavelength"].values, axes=1)
    for flat, expected in ((laser, at[450e-9].sensitivity), (white, lamp)):
        ratio = (flat / expected)[sl]
        assert np.std(ratio / ratio.mean()) < 2e-4  # the flux fluctuations' 5e-4 / sqrt(4) are common to all pixels
    assert np.std((laser / at[633e-9].sensitivity)[sl]) > 3e-3  # and not the 633 nm one
    # a 450 nm baseline's level is the sensitivity at 450 nm, its fringe the PRF there
    b = truth.sel(baseline="H1H4_450")
    frames = np.concatenate(list(simulation.acquisition_chunks(cfg, truth, kind="baseline", name="H1H4_450", start=0,
                                                               stop=3)))
    tips = dict(zip(truth["fiber"].values, truth["fiber_position"].values))
    prf = at[450e-9]
    phase, kx, ky = simulation.two_source_phase(*prf.centres(), tips["H1H4_450a"], tips["H1H4_450b"],
                                                wavelength=450e-9, pixel_pitch=cfg.metrology.pixel_pitch)
    envelope = truth["envelope"].values * truth["speckle"].sel(baseline="H1H4_450").values
    response = prf.fringe_response(kx, ky, phase=phase) * envelope * truth["visibility"].values
    model = (b["fringe_level"].values[:3, None, None] * prf.sensitivity * envelope
             + b["fringe_amplitude"].values[:3, None, None] * np.imag(response * np.exp(1j * b["phase"].values[:3,
                                                                                                         None, None])))
    np.testing.assert_allclose((frames - bias)[:, sl[0], sl[1]], model[:, sl[0], sl[1]], rtol=0, atol=2e-3)


def test_a_broadband_star_is_the_sum_of_its_monochromatic_images():
    cfg = chromatic_config()
    truth = simulation.make_truth(cfg)
    image = next(simulation.acquisition_chunks(cfg, truth, kind="position", name=2, start=0, stop=1))[0]
    image = (image - truth["bias"].values) / (1 + cfg.stars.flux_rsd * simulation._rng(cfg, "star flux", 2)
                                              .standard_normal(cfg.stars.frames)[0]) - cfg.stars.background
    p = truth.sel(position=2)
    expected = np.zeros_like(image)
    for w, share in zip(truth["wavelength"].values, truth["star_spectrum_weight"].values):
        prf = simulation.pixel_response(truth, float(w))
        expected += share * sum(cfg.stars.flux * prf.gaussian_response(float(x), float(y), cfg.stars.psf_sigma)
                                for x, y in zip(p["star_x"].values, p["star_y"].values))
    np.testing.assert_allclose(image, expected, rtol=0, atol=1e-6 * expected.max())
    # and not the image at 633 nm: the warm stars see the red side of the detector
    prf = simulation.pixel_response(truth)
    monochromatic = sum(cfg.stars.flux * prf.gaussian_response(float(x), float(y), cfg.stars.psf_sigma)
                        for x, y in zip(p["star_x"].values, p["star_y"].values))
    assert np.max(np.abs(monochromatic - expected)) > 1e-3 * expected.max()


def test_the_achromatic_twin_draws_the_same_noise():
    """The twin (amplitude 0, all else equal) differs from the chromatic bench by the response alone: the same
    photon and read noise draws, so that a comparison of the two sees colour, not noise. Every sample's photon
    noise is then a normal draw (gaussian_photons_above 0, as the chromatic study's bench has it): a Poisson
    draw's stream of random numbers depends on its mean, and the faint pixels' would not be the same."""

    def star_frames(amplitude, noisy):
        cfg = chromatic_config(amplitude=amplitude)
        if noisy:
            cfg = dataclasses.replace(cfg, detector=dataclasses.replace(cfg.detector, photon_noise=True,
                                                                        read_noise=4.0, gaussian_photons_above=0.0))
        return next(simulation.acquisition_chunks(cfg, simulation.make_truth(cfg), kind="position", name=1, start=0,
                                                  stop=2))

    noisy = star_frames(3.0, True) - star_frames(0.0, True)
    noiseless = star_frames(3.0, False) - star_frames(0.0, False)
    assert np.max(np.abs(noiseless)) > 10  # colour: tens of adu at the stars' peaks of 2e4 adu
    # the same draws: what is left of the noise is its amplitude's change with the signal, a fraction of an adu
    # (a difference of 40 adu in 2e4 changes sqrt(S / g) by 0.05 of a draw), against 49 adu for independent draws
    assert np.max(np.abs(noisy - noiseless)) < 1.0


def test_chromatic_keys_are_checked():
    with pytest.raises(ValueError, match=r"metrology.wavelengths: 633 is not a wavelength in metres"):
        simulation.SimulationConfig.from_dict({"metrology": {"wavelengths": [633]}})
    with pytest.raises(ValueError, match="stars.spectrum: unknown spectrum 'red'"):
        simulation.SimulationConfig.from_dict({"stars": {"spectrum": "red"}})
    with pytest.raises(ValueError, match="listed twice"):
        simulation.SimulationConfig.from_dict({"flats": {"wavelengths": [450e-9, 450.2e-9]}})
    with pytest.raises(ValueError, match="chromatic: surface_share"):
        simulation.SimulationConfig.from_dict({"chromatic": {"surface_share": 2.0}})

