"""Simulation studies of the paper's "Numerical simulations" section, one sweep point at a time.

A study is a self-contained simulation with known truth and its reduction:
the workflow runs one job per point of a sweep (config ``sweeps``), each
point a set of parameter values applied to the study's own simulated bench.

- :func:`offset_bias`: offset error maps against truth, the paper's method
  (:mod:`dice_core.paper_method`) beside ours, at one PRNU level (the paper's
  pixel-offset-bias figure).
- :func:`error_propagation`: centroid error per unit of one error source
  (:mod:`dice_core.error_budget`; the paper's table of error coefficients).
- :func:`stray_light`: a pair's offset errors under coherent stray light, detected and removed, against
  the field ratio, the laser's coherence length and the fiber tips' positions (issue 25).
- :func:`star_accuracy`: centroid accuracy of each calibration mode with
  perfect calibrations, against truth and by Procrustes (e.g. against the
  PRF width spread, which neither calibration sees).

Units: pixel, adu, relative where the parameter says so.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import tempfile
import time
from pathlib import Path

import numpy as np

from dice_core import centroids, fringe_fit, geometry, lazy, simulation
from dice_core.io import FrameStream, read_product
from dice_core.manifest import load_manifest
from dice_core.overrides import apply_dotted
from dice_core.paper_method import fit_baseline_paper

xr = lazy.module("xarray")

__all__ = ["OFFSET_BIAS_BENCH", "STAR_ACCURACY_BENCH", "TIP_TILT_BENCH", "STRAY_LIGHT_BENCH", "STRAY_LIGHT_VANES",
           "CHROMATIC_BENCH", "CALIBRATION_WAVELENGTHS", "CHROMATIC_MODES", "STUDIES", "star_accuracy", "tip_tilt",
           "stray_light", "chromatic_accuracy", "true_calibrations", "simulated_stacks", "offsets_error",
           "simulate_and_fit",
           "flat_metrology_centroids", "apply_overrides", "offset_bias", "affine_free", "error_propagation",
           "sweep_dataset", "sweep_from_dataset", "run_point"]

log = logging.getLogger(__name__)

#: The paper's simulated metrology bench (its "Metrology simulation results"): B = 10000 and
#: A = 6000 adu, 10 e-/adu, laser intensity 1e-2 RSD, fringe phase 1e-2 rad, plane waves, and
#: only a homogeneous Gaussian PRNU on the pixels: no dust, no bright bands, no PRF width spread,
#: a uniform fringe envelope and visibility. ``metrology.frames`` sets the photon noise: 30000
#: frames give the per-pixel floor of about 2e-5 pixel that the paper's maps show.
OFFSET_BIAS_BENCH = {
    "name": "offset-bias",
    "seed": 20150926,
    "frames_per_file": 10000,
    "detector": {"shape": [80, 84], "science_rows": [2, 79], "science_cols": [10, 83], "gain": 10.0,
                 "read_noise": 4.0, "prnu_rms": 2.0e-3, "offset_rms": 1.0e-3, "prf_width_spread": 0.0,
                 "dust_pixels": 0, "bright_bands": 0},
    "dark": {"frames": 2},
    "flats": {"frames": 2},
    "stars": {"positions": 1, "frames": 1},
    "metrology": {"frames": 30000, "mean_level": 10000.0, "amplitude": 6000.0, "laser_rsd": 1.0e-2,
                  "phase_jitter": 1.0e-2, "envelope_sigma": 1.0e6, "visibility_gradient": [0.0, 0.0],
                  "baselines": {"H1H4": {"period": 2.4, "angle_deg": 2.0}}, "pairs": {}},
}


def apply_overrides(base: dict, overrides: dict) -> dict:
    """A copy of a study's bench with dotted keys set: ``{"detector.prnu_rms": 5e-5}``
    (:func:`dice_core.overrides.apply_dotted`, which reads ``2e-3``, a string in YAML 1.1, as a number).

    Raises
    ------
    KeyError
        A dotted key whose parent section the bench does not have.
    ValueError
        A string that is not a number where the bench holds a number.
    """
    return apply_dotted(base, overrides, new_sections=False, what="study's bench")


def affine_free(values: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Values minus their least-squares plane over the pixels given (the offsets' gauge)."""
    return geometry.remove_modes(values, geometry.affine_basis(x, y))


def _offset_errors(cfg: simulation.SimulationConfig, workdir: Path, baseline: str, iterations: int):
    """Simulate one baseline into ``workdir``, fit it both ways; errors against truth (science pixels)."""
    t0 = time.perf_counter()
    manifest = load_manifest(simulation.simulate_dataset(cfg, workdir))
    truth = read_product(workdir / "truth.nc").load()
    log.info("simulated %d frames of %s (PRNU %.1e, photon noise %s) in %.1f s", cfg.metrology.frames, baseline,
             cfg.detector.prnu_rms, cfg.detector.photon_noise, time.perf_counter() - t0)
    stream = FrameStream(manifest.baselines[baseline], manifest.detector)
    dark = truth["bias"].values
    t0 = time.perf_counter()
    ours = fringe_fit.fit_baseline(stream, dark, detector=manifest.detector, flat=truth["sensitivity"].values,
                                   read_noise=truth["read_noise"].values, label=f"{baseline} (ours)")
    t1 = time.perf_counter()
    paper = fit_baseline_paper(stream, dark, detector=manifest.detector, iterations=iterations,
                               label=f"{baseline} (paper's method)")
    log.info("fits: ours %.1f s, the paper's %.1f s", t1 - t0, time.perf_counter() - t1)
    rows, cols = ours.rows, ours.cols
    x, y = cols.astype(float), rows.astype(float)

    def error(solution, offsets):
        n = solution.k / np.hypot(*solution.k)
        true = n[0] * truth["dx"].values[rows, cols] + n[1] * truth["dy"].values[rows, cols]
        ok = np.isfinite(offsets)
        out = np.full(rows.size, np.nan)
        out[ok] = offsets[ok] - affine_free(true[ok], x[ok], y[ok])
        return out

    # ours without a flat: the same factorisation under the PRNU-free gauge (no extra pass)
    errors = (error(ours, ours.offsets), error(paper, paper.offsets), error(ours, ours.offsets_prnu_free))
    return rows, cols, errors, ours.photon_floor, truth


def offset_bias(settings: dict, *, workdir, baseline: str = "H1H4", iterations: int = 4,
                noiseless_frames: int = 4000, noiseless_draws: int = 8) -> xr.Dataset:
    """Offset error maps of the paper's method and ours at one point (the pixel-offset-bias figure).

    The bench ``settings`` (a :class:`~dice_core.simulation.SimulationConfig`
    dict, e.g. :data:`OFFSET_BIAS_BENCH` with a point's overrides) is simulated
    with its photon and read noise (the maps the paper shows, the same noise
    for every point of a PRNU sweep), then ``noiseless_draws`` times without
    any noise (no photon or read noise, a steady laser and phase) at
    ``noiseless_frames`` frames, each with its own PRNU pattern of the same
    rms: the bias alone, which does not average down with the frames. The
    paper's method's bias follows the PRNU pattern's Fourier components at the
    fringe frequency, so it varies from one pattern to the next: the draws
    give its rms over patterns. Ours is given the true sensitivities as its
    reference flat (a perfect flat field); the paper's method uses none, as in
    the paper, and so does ``*_ours_no_flat``: ours under the PRNU-free gauge
    (the pixel contrast's smoothness) from the same fit.

    Returns
    -------
    xarray.Dataset
        ``error_ours``, ``error_paper`` (row, col): measured minus true
        projected offsets, pixel, with photon noise; ``bias_ours``,
        ``bias_paper`` (row, col): the same without noise, first draw;
        ``photon_floor`` (row, col); their rms over the science area as
        scalars (``rms_error_ours`` ..., the bias's over all draws); and
        ``draw_bias_ours``, ``draw_bias_paper``, ``draw_bias_ours_no_flat`` (draw):
        each draw's rms, pixel; ``*_ours_no_flat``: ours without a flat.
    """
    cfg = simulation.SimulationConfig.from_dict(settings)
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=workdir, prefix="noisy-") as folder:
        rows, cols, (error_ours, error_paper, error_free), floor, truth = _offset_errors(cfg, Path(folder), baseline,
                                                                                        iterations)
    steady = {"metrology.frames": noiseless_frames, "detector.photon_noise": False, "detector.read_noise": 0.0,
              "detector.dtype": "float32", "metrology.laser_rsd": 0.0, "metrology.amplitude_rsd": 0.0,
              "metrology.phase_jitter": 0.0}
    draws = []
    for draw in range(noiseless_draws):
        quiet_cfg = simulation.SimulationConfig.from_dict(apply_overrides(settings, {**steady,
                                                                                    "seed": cfg.seed + draw}))
        with tempfile.TemporaryDirectory(dir=workdir, prefix="noiseless-") as folder:
            q_rows, q_cols, biases, _, _ = _offset_errors(quiet_cfg, Path(folder), baseline, iterations)
        if not (np.array_equal(rows, q_rows) and np.array_equal(cols, q_cols)):
            raise RuntimeError("the noisy and noiseless fits cover different pixels")
        draws.append(biases)
    (bias_ours, bias_paper, bias_free), all_biases = draws[0], np.array(draws)  # (draw, method, pixel)
    shape = cfg.detector.shape

    def as_map(values):
        out = np.full(shape, np.nan)
        out[rows, cols] = values
        return out

    def rms(values):
        return float(np.sqrt(np.nanmean(np.square(values))))

    maps = {"error_ours": (error_ours, "projected offset error of ours, with photon noise"),
            "error_paper": (error_paper, "projected offset error of the paper's method, with photon noise"),
            "bias_ours": (bias_ours, "projected offset error of ours, noiseless"),
            "bias_paper": (bias_paper, "projected offset error of the paper's method, noiseless"),
            "error_ours_no_flat": (error_free, "projected offset error of ours without a flat (PRNU-free gauge), "
                                               "with photon noise"),
            "bias_ours_no_flat": (bias_free, "projected offset error of ours without a flat (PRNU-free gauge), "
                                             "noiseless"),
            "photon_floor": (floor, "per-pixel photon-noise floor of the offsets (ours)")}
    variables = {}
    for name, (values, what) in maps.items():
        variables[name] = (("row", "col"), as_map(values), {"units": "pixel", "long_name": what})
        variables[f"rms_{name}"] = ((), rms(values), {"units": "pixel", "long_name": f"rms over the science area: "
                                                                                     f"{what}"})
    for m, method in enumerate(("ours", "paper", "ours_no_flat")):
        per_draw = np.sqrt(np.nanmean(all_biases[:, m] ** 2, axis=1))
        variables[f"rms_bias_{method}"] = ((), float(np.sqrt(np.mean(per_draw**2))), {
            "units": "pixel", "long_name": f"{maps[f'bias_{method}'][1]}: rms over the science area and "
                                           f"{noiseless_draws} PRNU patterns"})
        variables[f"draw_bias_{method}"] = (("draw",), per_draw, {
            "units": "pixel", "long_name": f"{maps[f'bias_{method}'][1]}: rms over the science area, per PRNU pattern"})
    ds = xr.Dataset(variables, coords={"row": np.arange(shape[0]), "col": np.arange(shape[1])})
    ds.attrs.update({"prnu_rms": cfg.detector.prnu_rms, "measured_prnu_rms": float(truth["sensitivity"].values[
        rows, cols].std()), "frames": cfg.metrology.frames, "noiseless_frames": noiseless_frames,
        "noiseless_draws": noiseless_draws,
        "baseline": baseline, "paper_iterations": iterations})
    log.info("PRNU %.1e: rms error ours %.2e (without a flat %.2e), paper's %.2e, floor %.2e; noiseless bias ours "
             "%.2e (without a flat %.2e), paper's %.2e pixel", cfg.detector.prnu_rms, ds.rms_error_ours,
             ds.rms_error_ours_no_flat, ds.rms_error_paper, ds.rms_photon_floor, ds.rms_bias_ours,
             ds.rms_bias_ours_no_flat, ds.rms_bias_paper)
    return ds


# --------------------------------------------------------------------------- error propagation

def error_propagation(source: str, *, star: dict | None = None, amplitudes=None, trials: int = 400, seed: int = 0,
                      weighting: str = "pipeline") -> xr.Dataset:
    """One error source's Monte Carlo and analytic coefficients (:func:`dice_core.error_budget.sweep`).

    ``star`` overrides fields of :class:`dice_core.error_budget.Star` (PSF
    sigma and window half size in pixel, flux, background and read noise in
    electrons). Returns the sweep as a dataset (:func:`sweep_dataset`).
    """
    from dice_core import error_budget

    t0 = time.perf_counter()
    result = error_budget.sweep(source, amplitudes, trials=trials, seed=seed, weighting=weighting,
                                star=error_budget.Star(**(star or {})))
    log.info("%s: %d amplitudes x %d trials in %.1f s: per-axis coefficient %.4f +- %.4f (analytic %.4f), "
             "2-D %.4f", source, len(result.runs), trials, time.perf_counter() - t0, result.coefficient,
             result.error, result.prediction.coefficient, result.coefficient_2d)
    return sweep_dataset(result)


def sweep_dataset(result) -> xr.Dataset:
    """An :class:`dice_core.error_budget.Sweep` as a dataset: each trial's truth and error, pixel."""
    runs = result.runs
    data = {name: (("amplitude", "trial"), np.stack([getattr(r, name) for r in runs]),
                   {"units": "pixel", "long_name": what})
            for name, what in (("x", "true x"), ("y", "true y"), ("ex", "x error"), ("ey", "y error"))}
    ds = xr.Dataset(data, coords={"amplitude": ("amplitude", result.amplitudes, {
        "units": "pixel" if result.source == "offsets" else "1", "long_name": f"{result.source} amplitude"})})
    ds["coefficient"] = ((), result.coefficient, {"units": "pixel per unit amplitude",
                                                  "long_name": "per-axis Monte Carlo coefficient"})
    ds["error"] = ((), result.error, {"units": "pixel per unit amplitude", "long_name": "its 1-sigma error"})
    ds.attrs.update({"error_source": result.source, "weighting": result.weighting,
                     "analytic_x": result.prediction.coefficient_x, "analytic_y": result.prediction.coefficient_y,
                     "cramer_rao": np.nan if result.cramer_rao is None else result.cramer_rao,
                     })
    for key, value in dataclasses.asdict(result.star).items():
        ds.attrs[f"star_{key}"] = value
    return ds


def sweep_from_dataset(ds: xr.Dataset):
    """The :class:`dice_core.error_budget.Sweep` that :func:`sweep_dataset` wrote."""
    from dice_core import error_budget

    source, weighting = ds.attrs["error_source"], ds.attrs["weighting"]
    runs = tuple(error_budget.MonteCarlo(source, float(a), weighting, *(ds[v].values[i] for v in ("x", "y", "ex", "ey")))
                 for i, a in enumerate(ds["amplitude"].values))
    star = error_budget.Star(**{f.name: type(f.default)(ds.attrs[f"star_{f.name}"])
                                for f in dataclasses.fields(error_budget.Star)})
    bound = float(ds.attrs["cramer_rao"])
    return error_budget.Sweep(source, weighting, runs,
                              error_budget.Analytic(source, weighting, float(ds.attrs["analytic_x"]),
                                                    float(ds.attrs["analytic_y"])),
                              None if np.isnan(bound) else bound, star)


# --------------------------------------------------------------------------- star accuracy

#: The default preset's detector and stars, without noise, with perfect calibrations: what limits the
#: centroids when the flat and the metrology are exact (e.g. the PRF width spread, which neither sees).
#: No tip-tilt (the roll stays, which Procrustes absorbs): the Procrustes accuracies see only the pixels. Set ``detector.photon_noise:
#: true`` (with a read noise) for the noisy case, ``stars.tip_tilt_pv`` for the stage.
STAR_ACCURACY_BENCH = {
    "name": "star-accuracy",
    "seed": 20150926,
    "detector": {"shape": [80, 84], "science_rows": [2, 79], "science_cols": [10, 83], "prnu_rms": 2.0e-3,
                 "offset_rms": 1.0e-3, "prf_width_spread": 0.01, "photon_noise": False, "read_noise": 0.0,
                 "dtype": "float32"},
    "dark": {"frames": 2},
    "flats": {"frames": 2},
    "metrology": {"frames": 2, "baselines": {"H1H4": {"period": 2.4, "angle_deg": 2.0}}, "pairs": {}},  # unused
    "stars": {"positions": 12, "frames": 16, "tip_tilt_pv": 0.0},  # a roll only: Procrustes absorbs it
}

# the modes a perfect flat, offsets and widths calibrate (the chromatic ones have a study of their own)
STAR_ACCURACY_MODES = tuple(name for name, mode in centroids.MODES.items() if mode.needs <= {"flat", "offsets",
                                                                                              "widths"})


def _position_chunks(cfg, truth, index: int):
    """A star position's simulated frames as :class:`dice_core.io.Chunk` s, in memory (no file)."""
    from dice_core.io import Chunk

    start = 0
    for frames in simulation.acquisition_chunks(cfg, truth, kind="position", name=index, start=0,
                                                stop=cfg.stars.frames):
        frames = np.asarray(frames, dtype=np.float64)
        yield Chunk(start, frames, np.zeros(frames.shape, bool), False)
        start += frames.shape[0]


def simulated_stacks(settings: dict, *, batches: int = 4, label: str = "bench"):
    """A bench's star positions simulated in memory: (config, truth, manifest, position indices, stacks)."""
    from dice_core import stacks
    from dice_core.manifest import parse_manifest

    cfg = simulation.SimulationConfig.from_dict(settings)
    truth = simulation.make_truth(cfg)
    manifest = parse_manifest(simulation.dataset_layout(cfg), Path.cwd() / f"{label}.yaml")
    positions = [p.index for p in manifest.positions]
    position_stacks = [stacks.stack_position(_position_chunks(cfg, truth, i), cfg.stars.frames, n_batches=batches,
                                             position=i, label=f"position {i}") for i in positions]
    return cfg, truth, manifest, positions, position_stacks


def pixel_scale_map(values, mask, *, degree: int = 6) -> np.ndarray:
    """A map (row, col) less its least-squares polynomial of ``degree`` over ``mask`` (zero outside): what
    :func:`dice_core.prf.width_maps` can measure of a width or variance map (the mean and the smooth part are the
    fringe visibility's)."""
    from dice_core import prf

    rows, cols = np.nonzero(mask)
    out = np.zeros(mask.shape)
    out[mask] = prf.pixel_scale(np.asarray(values)[mask], cols, rows, degree=degree)
    return out


def _measurable_variances(truth, detector, *, degree: int = 6):
    """The true PRF variances (x, y) minus their smooth polynomial over the science area, pixel^2, without the
    maps' photon noise: the width mode's perfect calibration."""
    mask = detector.science_mask()
    return [pixel_scale_map(truth[f"width_{axis}"].values ** 2, mask, degree=degree) for axis in "xy"]


def star_accuracy(settings: dict, *, modes=STAR_ACCURACY_MODES, method: str = "gaussian", half_size: int = 7,
                  batches: int = 4, groups: int = 3, trials: int = 500) -> xr.Dataset:
    """Centroid accuracy of each calibration mode with perfect calibrations, against truth and by Procrustes.

    The bench ``settings`` (:data:`STAR_ACCURACY_BENCH` with a point's
    overrides) is simulated in memory, star positions only, with its true
    sensitivities as the flat, its true pixel offsets as the metrology and
    its true PRF variances, less their smooth part (what the width maps
    measure), as the widths: each mode's error is then what the calibrations it uses cannot remove.
    The dark is the true bias and the frames are not quantised (the
    workflow's uint16 files add about 0.3 adu rms).

    Returns
    -------
    xarray.Dataset
        Per mode: ``truth_error`` (rms over positions, stars and both axes of
        the centroid minus the true position, each position's mean
        displacement removed, pixel); ``accuracy_position``,
        ``error_position``, ``accuracy_group``, ``error_group`` (the accuracy
        table's Procrustes numbers, pixel).
    """
    from dice_core import accuracies, centroids

    t0 = time.perf_counter()
    cfg, truth, manifest, positions, position_stacks = simulated_stacks(settings, batches=batches,
                                                                        label="star-accuracy")
    log.info("simulated %d positions of %d frames in %.1f s (PRF width spread %.3g, photon noise %s)",
             len(positions), cfg.stars.frames, time.perf_counter() - t0, cfg.detector.prf_width_spread,
             cfg.detector.photon_noise)
    read_noise = np.maximum(truth["read_noise"].values, 1e-3)  # the noise weights need a floor
    datasets, truth_errors = {}, []
    for mode in modes:
        use_flat, use_metrology = centroids.mode_corrections(mode)
        widths = {}
        if "widths" in centroids.mode_needs(mode):  # the PRF variances the width maps can measure
            widths = dict(zip(("variance_x", "variance_y"), _measurable_variances(truth, manifest.detector)))
        result = centroids.measure_positions(
            position_stacks, positions, approx=manifest.star_approx, detector=manifest.detector,
            dark=truth["bias"].values, read_noise=read_noise, prnu=truth["sensitivity"].values if use_flat else None,
            dx=truth["dx"].values if use_metrology else None, dy=truth["dy"].values if use_metrology else None,
            method=method, half_size=half_size, label=f"mode {mode}", log=log, **widths)
        datasets[mode] = centroids.centroids_dataset(result, positions, mode=mode, method=method)
        errors = np.stack([result.x - truth["star_x"].values, result.y - truth["star_y"].values])
        errors -= np.nanmean(errors, axis=2, keepdims=True)  # each position's common displacement
        truth_errors.append(float(np.sqrt(np.nanmean(errors**2))))
    table = {}
    for mode, found in datasets.items():  # accuracies.mode_accuracies, for names that are not all modes
        configurations = accuracies.select_positions(found)[0]
        for grouping, data in (("position", configurations),
                               ("group", accuracies.group_means(configurations, groups))):
            result = accuracies.accuracy(data, trials=trials)
            table[mode, grouping] = {"accuracy": result.accuracy, "error": result.error}
    dims = ("mode",)
    ds = xr.Dataset({"truth_error": (dims, truth_errors, {"units": "pixel", "long_name": "rms centroid error against "
                                                          "truth, each position's mean displacement removed"})},
                    coords={"mode": np.array(list(modes), dtype=str)})  # (str: an empty list's would be float)
    for grouping in ("position", "group"):
        for field_, what in (("accuracy", "corrected Procrustes accuracy"), ("error", "its 1-sigma error")):
            ds[f"{field_}_{grouping}"] = (dims, [table[m, grouping][field_] for m in modes], {
                "units": "pixel", "long_name": f"{what} over {grouping}s"})
    ds.attrs.update({"method": method, "prf_width_spread": cfg.detector.prf_width_spread,
                     "positions": len(positions), "frames": cfg.stars.frames})
    for mode, value in zip(modes, truth_errors):
        log.info("mode %-15s error against truth %.2e pixel, accuracy (p) %.2e +- %.1e pixel", mode, value,
                 table[mode, "position"]["accuracy"], table[mode, "position"]["error"])
    return ds


# --------------------------------------------------------------------------- tip-tilt against the superimpositions

#: The tip-tilt study's bench: the star-accuracy bench (perfect flat and metrology, no photon noise:
#: only the PRF width spread's pixelation is left) on the simulated stage, its field 2 degrees off axis
#: at 25000 pixel; a point sets ``stars.tip_tilt_pv`` and ``stars.positions``.
TIP_TILT_BENCH = STAR_ACCURACY_BENCH


def flat_metrology_centroids(settings: dict, *, method: str = "gaussian", half_size: int = 7, batches: int = 4):
    """Flat+metrology centroids of a simulated bench (true calibrations), the truth and the pose geometry.

    Returns
    -------
    configurations : ndarray (position, star, 2)
        Centroids, pixel.
    truth : xarray.Dataset
        The simulation's truth (``stage_rotation``: tip, tilt, roll in rad).
    geometry : dice_core.superimposition.PoseGeometry
        The simulated bench's distance, off-axis angle and detector centre.
    """
    from dice_core import centroids, superimposition

    cfg, truth, manifest, positions, position_stacks = simulated_stacks(settings, batches=batches, label="tip-tilt")
    result = centroids.measure_positions(
        position_stacks, positions, approx=manifest.star_approx, detector=manifest.detector, dark=truth["bias"].values,
        read_noise=np.maximum(truth["read_noise"].values, 1e-3), prnu=truth["sensitivity"].values,
        dx=truth["dx"].values, dy=truth["dy"].values, method=method, half_size=half_size, label="flat+metrology")
    rows, cols = cfg.detector.shape
    geometry = superimposition.PoseGeometry(distance=cfg.stars.distance, off_axis=np.radians(cfg.stars.off_axis_deg),
                                            centre=((cols - 1) / 2, (rows - 1) / 2))
    return np.stack([result.x, result.y], axis=-1), truth, geometry


def tip_tilt(settings: dict, *, models=("procrustes", "projective", "pose"), trials: int = 1000,
             method: str = "gaussian", pose_off_axis_deg: float | None = None) -> xr.Dataset:
    """Each superimposition's flat+metrology accuracy under the bench's tip-tilt, its excess, the pose's bounds.

    The bench (:data:`TIP_TILT_BENCH` with a point's overrides) is simulated
    twice with the same seed and detector: as set, and with no tip-tilt
    (its twin). Per model: the corrected accuracy over positions and its
    error, and the excess variance accuracy^2 - twin's accuracy^2 (pixel^2).
    For the pose model also its identifiability (:func:`dice_core.superimposition.pose_identifiability`):
    the tip and tilt SNR, whether identifiable (1/0), their rms Cramer-Rao
    bounds from the data alone and with the field's direction known, and the
    rms of fitted minus true tip and tilt (rad); and what it removes of
    Procrustes's excess (:func:`tip_tilt_removals`). ``pose_off_axis_deg``:
    the pose's nominal off-axis angle, degrees, where it is not the bench's
    (the simulated one unless set).
    """
    from dice_core import accuracies, superimposition

    twin = apply_overrides(settings, {"stars.tip_tilt_pv": 0.0})
    configurations, truth, geometry = flat_metrology_centroids(settings, method=method)
    untilted, *_ = flat_metrology_centroids(twin, method=method)
    if pose_off_axis_deg is not None:
        geometry = dataclasses.replace(geometry, off_axis=np.radians(pose_off_axis_deg))
    ds = xr.Dataset(coords={"model": list(models)})
    accuracy, error, excess, results = [], [], [], {}
    for model in models:
        result = accuracies.accuracy(configurations, model=model, geometry=geometry, trials=trials)
        reference = accuracies.accuracy(untilted, model=model, geometry=geometry, trials=trials)
        results[model] = (result, reference)
        accuracy.append(result.accuracy)
        error.append(result.error)
        excess.append(result.accuracy**2 - reference.accuracy**2)
        if model == "pose":
            report = superimposition.pose_identifiability(result.result, sigma=result.accuracy)
            true = truth["stage_rotation"].values
            for k, angle in ((3, "tip"), (4, "tilt")):
                rms = float(np.sqrt(np.mean((result.result.poses[:, k] - true[:, k - 3]) ** 2)))
                ds[f"pose_{angle}_snr"] = ((), report.snr[angle], {"units": "1", "long_name": f"{angle} variation "
                                           "over positions in Cramer-Rao bounds"})
                ds[f"pose_{angle}_identifiable"] = ((), int(report.identifiable[angle]), {
                    "units": "1", "long_name": f"1 if the data identify the {angle}, else 0"})
                ds[f"pose_{angle}_crlb"] = ((), float(np.sqrt(np.mean(report.crlb[:, k] ** 2))), {
                    "units": "rad", "long_name": f"rms Cramer-Rao bound of the {angle} from the data alone"})
                ds[f"pose_{angle}_crlb_nominal_field"] = ((), float(np.sqrt(np.mean(report.crlb_nominal_field[:, k] ** 2))), {
                    "units": "rad", "long_name": f"rms Cramer-Rao bound of the {angle}, the field's direction known"})
                ds[f"pose_{angle}_error"] = ((), rms, {"units": "rad", "long_name": f"rms fitted minus true {angle}"})
                ds[f"true_{angle}_rms"] = ((), float(np.sqrt(np.mean(true[:, k - 3] ** 2))), {
                    "units": "rad", "long_name": f"rms of the true {angle} over positions"})
    ds["accuracy"] = (("model",), accuracy, {"units": "pixel", "long_name": "corrected flat+metrology accuracy over "
                                             "positions"})
    ds["error"] = (("model",), error, {"units": "pixel", "long_name": "its 1-sigma Monte Carlo error"})
    ds["excess_variance"] = (("model",), excess, {"units": "pixel^2", "long_name": "accuracy^2 minus the untilted "
                                                  "twin's accuracy^2"})
    if "pose" in results and "procrustes" in results:
        removals = tip_tilt_removals(results["procrustes"], results["pose"], tilted=configurations, untilted=untilted,
                                     true_tip_tilt=truth["stage_rotation"].values[:, :2], trials=trials)
        for name, (value, what) in removals.items():
            ds[name] = ((), value, {"units": "1", "long_name": what})
    ds.attrs.update({"method": method, "positions": configurations.shape[0],
                     "pose_off_axis_deg": float(np.degrees(geometry.off_axis))})
    return ds


def tip_tilt_removals(procrustes, pose, *, tilted, untilted, true_tip_tilt, trials: int = 1000) -> dict:
    """What the pose removes of Procrustes's tip-tilt excess on twins, beside what the data allow (issue 27).

    Parameters
    ----------
    procrustes, pose : (Accuracy, Accuracy)
        Each model's accuracies of the tilted twin and of the untilted one
        (:func:`dice_core.accuracies.accuracy`).
    tilted, untilted : ndarray (position, star, 2)
        The twins' centroids, pixel: the tilted minus the untilted is the tip-tilt's true signature (the
        twins share their noise).
    true_tip_tilt : ndarray (position, 2)
        The simulated tip and tilt, rad.

    Returns
    -------
    dict
        Name -> (value, meaning): ``pose_removal``, the measured share,
        1 - pose excess / Procrustes excess; ``pose_removal_true_tip_tilt``,
        the share removed when the true tip and tilt are given (the tilted
        twin corrected by the pose model's signature of them, with the pose's
        other fitted parameters, then Procrustes); ``pose_removal_bound``,
        the noise-limited bound from the pose's Fisher information on the
        twins' true signature, and ``pose_removal_bound_data`` from the data
        alone (:func:`dice_core.superimposition.tip_tilt_removal`);
        ``pose_tip_tilt_snr``; ``pose_removal_over_bound``.
    """
    from dice_core import accuracies, superimposition

    (p_tilted, p_untilted), (q_tilted, q_untilted) = procrustes, pose
    excess = p_tilted.accuracy**2 - p_untilted.accuracy**2
    measured = 1 - (q_tilted.accuracy**2 - q_untilted.accuracy**2) / excess
    given = tilted - superimposition.tip_tilt_signature(q_tilted.result, true_tip_tilt)
    oracle = 1 - (accuracies.accuracy(given, model="procrustes", trials=trials).accuracy**2
                  - p_untilted.accuracy**2) / excess
    options = dict(sigma=q_tilted.accuracy, factor=p_tilted.factor)
    exact = superimposition.tip_tilt_removal(q_tilted.result, p_tilted.result, signature=tilted - untilted, **options)
    data = superimposition.tip_tilt_removal(q_tilted.result, p_tilted.result, **options)
    return {"pose_removal": (measured, "share of Procrustes's tip-tilt excess the pose removes, measured on the "
                                       "twins"),
            "pose_removal_true_tip_tilt": (oracle, "share removed with the true tip and tilt given (the pose "
                                                   "model's signature of them subtracted, then Procrustes)"),
            "pose_removal_bound": (exact.bound, "noise-limited share from the pose's Fisher information, the twins' "
                                                "true signature"),
            "pose_removal_bound_data": (data.bound, "noise-limited share from the pose's Fisher information, the "
                                                    "data alone"),
            "pose_tip_tilt_snr": (exact.snr, "the tip-tilt signature Procrustes leaves over its noise part"),
            "pose_removal_over_bound": (measured / exact.bound if exact.bound > 0 else np.nan,
                                        "measured share over the noise-limited bound")}


# --------------------------------------------------------------------------- coherent stray light

#: Vane edges of the stray-light study's bench, two a baseline (one copying each fiber's wave): directions
#: 2.5-6 mrad off their fiber's seen from the detector centre, 0.40-0.55 m above it, extra paths 0.6-1.5 cm
#: (the paper: "around 1 cm plus or minus a factor 2").
STRAY_LIGHT_VANES = [
    {"fiber": "H1H4a", "offset_mrad": [4.0, 2.5], "distance": 0.45, "extra_path": 0.008},
    {"fiber": "H1H4b", "offset_mrad": [-6.0, 3.0], "distance": 0.52, "extra_path": 0.015},
    {"fiber": "V1V4a", "offset_mrad": [3.0, -5.0], "distance": 0.40, "extra_path": 0.006},
    {"fiber": "V1V4b", "offset_mrad": [-2.5, -7.0], "distance": 0.55, "extra_path": 0.012},
]

#: The stray-light study's bench: the default preset's detector, noise and pair P14 (spherical fringes from
#: fibers 600 mm away), 2000 frames a baseline (a per-pixel floor of 7.5e-5 pixel), the vanes above at the
#: paper's field ratio 1e-3 and a HeNe's coherence (30 cm: every vane coherent).
STRAY_LIGHT_BENCH = {
    "name": "stray-light",
    "seed": 20150926,
    "frames_per_file": 100000,
    "detector": {"shape": [80, 84], "science_rows": [2, 79], "science_cols": [10, 83]},
    "dark": {"frames": 2},
    "flats": {"frames": 2},
    "stars": {"positions": 1, "frames": 1},
    "metrology": {"frames": 2000, "spherical": True,
                  "baselines": {"H1H4": {"period": 2.4, "angle_deg": 2.0, "midpoint": [0.012, 0.006]},
                                "V1V4": {"period": 2.4, "angle_deg": 93.0, "midpoint": [-0.004, 0.008]}},
                  "pairs": {"P14": ["H1H4", "V1V4"]}},
    "stray_light": {"field_ratio": 1e-3, "coherence_length": 0.3, "sources": STRAY_LIGHT_VANES},
}


def _tip_grid(positions: int, step: float) -> list:
    """The fiber-tip shifts (x, y, 0), m: the unshifted tips alone, or a square grid of ``positions`` (9: 3x3)
    of ``step`` about them."""
    side = int(round(np.sqrt(positions)))
    if side * side != positions:
        raise ValueError(f"tip_positions must be a square number (1, 9...), got {positions}")
    offsets = (np.arange(side) - (side - 1) / 2) * step
    return [(float(dx), float(dy), 0.0) for dy in offsets for dx in offsets]


def simulate_and_fit(cfg, workdir):
    """Simulate ``cfg`` into ``workdir`` and fit every baseline with the true sensitivities as the flat (and the
    manifest's fiber tips, with spherical waves): (manifest, truth, {baseline: (solution, metrology product)})."""
    from dice_core import fringes

    manifest = load_manifest(simulation.simulate_dataset(cfg, workdir))
    truth = read_product(Path(workdir) / "truth.nc").load()
    products = {}
    for baseline in manifest.baselines:
        bench = None if manifest.geometry is None else geometry.BaselineGeometry.of_baseline(manifest.geometry,
                                                                                           baseline)
        solution = fringe_fit.fit_baseline(
            FrameStream(manifest.baselines[baseline], manifest.detector), truth["bias"].values,
            detector=manifest.detector, flat=truth["sensitivity"].values, read_noise=truth["read_noise"].values,
            geometry=bench, label=baseline)
        products[baseline] = (solution, fringes.solution_dataset(
            solution, manifest.detector, fibers=None if bench is None else bench.fibers))
    return manifest, truth, products


def _stray_light_position(cfg, workdir):
    """One tip position: simulate ``cfg``, fit its pair, and its offsets with the stray light detected (left in)
    and removed: each one's errors against the truth (the affine part and its declared modes removed from the
    truth), (row, col) maps; the floors; the components found; the truth's stray-light offset error rms."""
    from dice_core import deprojection
    from dice_core import stray_light as stray_light_module

    manifest, truth, products = simulate_and_fit(cfg, workdir)
    (pair, (first, second)), = manifest.pairs.items()
    fitted = {baseline: product for baseline, (_, product) in products.items()}
    found = [stray_light_module.stray_light_dataset(fitted[b], baseline=b) for b in (first, second)]
    out = {"components": sum(int(f["n_components"]) for f in found)}
    for way, stray in (("detect", (None, None)), ("remove", found)):
        offsets = deprojection.offsets_dataset(fitted[first], fitted[second], stray=stray, label=pair)
        out[way] = offsets_error(offsets, truth)
        out["floor"] = [float(np.sqrt(np.nanmean(offsets[f"{a}_photon_noise_floor"].values ** 2)))
                        for a in ("dx", "dy")]
    return out


def offsets_error(offsets, truth):
    """A pair's dx, dy (``calibration/offsets_<pair>.nc``) minus the truth, the affine part of (dx, dy) and
    the product's declared modes removed from the truth: (2, row, col) maps, pixel, NaN outside the finite
    pixels."""
    good = np.isfinite(offsets["dx"].values) & np.isfinite(offsets["dy"].values)
    rows, cols = np.nonzero(good)
    n = rows.size
    zeros = np.zeros((3, n))
    affine = geometry.affine_basis(cols, rows)
    fields = [*np.hstack([affine, zeros]), *np.hstack([zeros, affine])]
    if "unobservable_dx" in offsets:
        fields += list(np.concatenate([offsets["unobservable_dx"].values[:, good],
                                       offsets["unobservable_dy"].values[:, good]], axis=1))
    true = np.concatenate([truth["dx"].values[good], truth["dy"].values[good]])
    error = np.concatenate([offsets["dx"].values[good], offsets["dy"].values[good]]) - geometry.remove_modes(
        true, np.array(fields))
    maps = np.full((2, *good.shape), np.nan)
    maps[0][good], maps[1][good] = error[:n], error[n:]
    return maps


def stray_light(settings: dict, *, workdir, tip_positions: int = 1, tip_step: float = 0.0,
                path_scale: float = 1.0) -> xr.Dataset:
    """Offset errors of a pair under coherent stray light, with and without its removal (issue 25).

    The bench ``settings`` (:data:`STRAY_LIGHT_BENCH` with a point's overrides: ``stray_light.field_ratio``,
    ``stray_light.coherence_length``...) is simulated at ``tip_positions`` fiber-tip positions (1, or a square
    grid such as the paper's 9, ``tip_step`` m apart: every tip moved, true and nominal, the vanes fixed, each
    position an acquisition of its own, with its own noise) and
    reduced at each: its pair's dx, dy against the truth, the stray light left in (detect) and taken out
    (remove), each with the affine part and its own declared modes removed from the truth. With several
    positions, the maps are averaged, as the paper did, and so are their errors. ``path_scale`` multiplies
    every source's extra path (0.03: the sub-millimetre paths of edges diffracting close to the beams, where
    the 0.6-1.5 cm of the vanes are reflections').

    Returns
    -------
    xarray.Dataset
        Scalars, pixel: ``error_dx_detect``, ``error_dy_detect``, ``error_dx_remove``, ``error_dy_remove``
        (rms over the pixels, the first position), ``floor_dx``, ``floor_dy`` (rms photon-noise floors there);
        with several positions ``average_error_*`` (the same of the averaged maps) and ``average_floor_*``
        (the floors over sqrt(positions)); ``components`` found (first position), ``field_ratio``,
        ``coherence_length`` (m, NaN: coherent) and each vane's ``coherence`` of its parasitic fringe.
    """
    settings = json.loads(json.dumps(settings))
    for source in settings.get("stray_light", {}).get("sources", []):
        source["extra_path"] = source["extra_path"] * path_scale
    base = simulation.SimulationConfig.from_dict(settings)
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    results = []
    for index, shift in enumerate(_tip_grid(tip_positions, tip_step)):
        # each position its own acquisition: the same noise would make the positions' photon-noise errors
        # correlate as cos(K . shift), which a grid's mean cancels far below the floor / sqrt(positions)
        cfg = simulation.SimulationConfig.from_dict(apply_dotted(
            base.to_dict(), {"metrology.tip_shift": list(shift), "metrology.acquisition": index},
            what="stray-light bench"))
        t0 = time.perf_counter()
        with tempfile.TemporaryDirectory(dir=workdir, prefix="tips-") as folder:
            results.append(_stray_light_position(cfg, folder))
        log.info("tips shifted by (%.2f, %.2f) mm: dx error %.2e (detect), %.2e (remove), floor %.2e pixel; %d "
                 "component(s) in %.1f s", shift[0] * 1e3, shift[1] * 1e3,
                 np.sqrt(np.nanmean(results[-1]["detect"][0] ** 2)), np.sqrt(np.nanmean(results[-1]["remove"][0] ** 2)),
                 results[-1]["floor"][0], results[-1]["components"], time.perf_counter() - t0)
    ds = xr.Dataset()

    def scalar(name, value, units, meaning):
        ds[name] = ((), float(value), {"units": units, "long_name": meaning})

    first = results[0]
    for i, axis in enumerate(("dx", "dy")):
        for way in ("detect", "remove"):
            scalar(f"error_{axis}_{way}", np.sqrt(np.nanmean(first[way][i] ** 2)), "pixel",
                   f"rms of {axis} minus truth, stray light {'left in' if way == 'detect' else 'removed'}")
            if len(results) > 1:
                average = np.mean([r[way][i] for r in results], axis=0)
                scalar(f"average_error_{axis}_{way}", np.sqrt(np.nanmean(average**2)), "pixel",
                       f"the same of {axis} averaged over the {len(results)} tip positions")
        scalar(f"floor_{axis}", first["floor"][i], "pixel", f"rms photon-noise floor of {axis}")
        if len(results) > 1:
            scalar(f"average_floor_{axis}", np.sqrt(np.mean([r["floor"][i] ** 2 for r in results]) / len(results)),
                   "pixel", f"the floor of the averaged {axis}")
    scalar("components", first["components"], "1", "stray-light components found in the pair's baselines")
    scalar("field_ratio", base.stray_light.field_ratio, "1", "field ratio of the vanes")
    scalar("coherence_length", np.nan if base.stray_light.coherence_length is None else
           base.stray_light.coherence_length, "m", "coherence length of the laser (NaN: coherent)")
    scalar("tip_positions", len(results), "1", "fiber-tip positions averaged")
    scalar("tip_step", tip_step, "m", "their spacing")
    scalar("path_scale", path_scale, "1", "factor on the vanes' extra paths")
    return ds


# --------------------------------------------------------------------------- chromatic pixels (issue 26)

#: The calibration wavelengths (m) of the chromatic study by their number: 633 nm alone (the paper's HeNe), then
#: a blue one, a red one and two more spread over the band (docs/centroids.md, "Chromatic pixels").
CALIBRATION_WAVELENGTHS = {1: (633e-9,), 2: (450e-9, 633e-9), 3: (450e-9, 633e-9, 800e-9),
                           5: (420e-9, 500e-9, 633e-9, 700e-9, 800e-9)}

#: The chromatic study's bench: the default detector (PRNU 2e-3, offsets 1e-3 pixel, PRF width spread 1%) made
#: chromatic (amplitude 5: the changes from 633 to 400 nm five times those, dice_core.chromatic), broadband
#: stars (flat spectrum, 400-800 nm) at the paper's geometry and photon limit: 33 positions 0.17 pixel apart,
#: about 3e-5 pixel a position (16 frames of stars 54 times the default's flux: float32 frames, the saturation
#: out of reach), no tip-tilt. Every calibration wavelength of :data:`CALIBRATION_WAVELENGTHS` is on the truth's
#: grid (as laser flats), so that every number of wavelengths sees the same frames; every sample's photon noise is
#: a normal draw (gaussian_photons_above 0), so that the achromatic twin draws exactly the same noise.
CHROMATIC_BENCH = {
    "name": "chromatic",
    "seed": 20150926,
    "detector": {"shape": [80, 84], "science_rows": [2, 79], "science_cols": [10, 83], "prnu_rms": 2.0e-3,
                 "offset_rms": 1.0e-3, "prf_width_spread": 0.01, "saturation": 1.0e9, "dtype": "float32",
                 "gaussian_photons_above": 0.0},
    "dark": {"frames": 2},
    "flats": {"frames": 2, "wavelengths": sorted({w for ws in CALIBRATION_WAVELENGTHS.values() for w in ws})},
    "metrology": {"frames": 2, "baselines": {"H1H4": {"period": 2.4, "angle_deg": 2.0}}, "pairs": {}},  # unused
    "stars": {"positions": 33, "frames": 16, "flux": 1.35e7, "tip_tilt_pv": 0.0, "spectrum": "flat"},
    "chromatic": {"amplitude": 5.0},
}

#: The chromatic study's modes besides the chromatic one: the paper's at 633 nm on the chromatic detector, and the
#: achromatic twin's raw and flat+metrology.
CHROMATIC_MODES = ("raw", "flat", "flat+metrology", "achromatic raw", "achromatic flat+metrology")


def true_calibrations(truth: xr.Dataset, wavelength_sets: dict, *, spectrum, mask) -> dict:
    """Perfect calibrations of a simulated bench, by mode: measure_positions' prnu, dx, dy (and variances).

    The flat is the white flat's sensitivity (the lamp's spectrum, ``flat_spectrum_weight``), the offsets are
    those at metrology.wavelength (the truth's dx, dy), and the chromatic mode's, one per entry of
    ``wavelength_sets`` (a name -> calibration wavelengths, m; the mode ``chromatic <name>``), are the effective
    response to ``spectrum`` (samples, weights) of the true maps at those wavelengths
    (:func:`dice_core.chromatic.effective_response`): the sensitivities from them where there are two or more
    (laser flats), else the white flat's, and the PRF variances' change from metrology.wavelength's as the width
    maps measure it (its pixel-scale part over ``mask``, the science area).
    """
    from dice_core import chromatic

    white = np.tensordot(truth["flat_spectrum_weight"].values, truth["sensitivity_wavelength"].values, axes=1)
    out = {"raw": {}, "flat": {"prnu": white},
           "flat+metrology": {"prnu": white, "dx": truth["dx"].values, "dy": truth["dy"].values}}
    for name, wavelengths in wavelength_sets.items():
        at = truth.sel(wavelength=list(wavelengths), method="nearest")
        several = len(wavelengths) >= 2
        effective = chromatic.effective_response(
            wavelengths, {n: at[f"{n}_wavelength"].values for n in ("dx", "dy", "width_x", "width_y")},
            spectrum=spectrum, sensitivity=at["sensitivity_wavelength"].values if several else white,
            sensitivity_wavelengths=wavelengths if several else None)
        change = {f"variance_{axis}": pixel_scale_map(getattr(effective, f"variance_{axis}")
                                                      - truth[f"width_{axis}"].values ** 2, mask) for axis in "xy"}
        out[f"chromatic {name}"] = {"prnu": effective.sensitivity, "dx": effective.dx, "dy": effective.dy, **change}
    return out


def _mode_centroids(truth, manifest, positions, position_stacks, calibrations: dict, *, method, half_size, label):
    """{mode: its centroids dataset} and {mode: its rms error against truth (each position's mean displacement
    removed), pixel} of a simulated bench under the given calibrations (mode -> measure_positions' maps)."""
    from dice_core import centroids

    datasets, errors = {}, {}
    read_noise = np.maximum(truth["read_noise"].values, 1e-3)  # the noise weights need a floor
    for mode, calibration in calibrations.items():
        result = centroids.measure_positions(
            position_stacks, positions, approx=manifest.star_approx, detector=manifest.detector,
            dark=truth["bias"].values, read_noise=read_noise, method=method, half_size=half_size,
            label=f"{label} {mode}", **calibration)
        datasets[mode] = centroids.centroids_dataset(result, positions, mode=mode, method=method)
        error = np.stack([result.x - truth["star_x"].values, result.y - truth["star_y"].values])
        error -= np.nanmean(error, axis=2, keepdims=True)
        errors[mode] = float(np.sqrt(np.nanmean(error**2)))
    return datasets, errors


def _accuracy_table(datasets: dict, *, groups: int, trials: int) -> dict:
    """{(name, grouping): (accuracy, error)} of centroid datasets by any name (accuracies.mode_accuracies takes
    modes only), Procrustes over positions and over groups of positions, pixel."""
    from dice_core import accuracies

    table = {}
    for name, found in datasets.items():
        configurations = accuracies.select_positions(found)[0]
        for grouping, data in (("position", configurations),
                               ("group", accuracies.group_means(configurations, groups))):
            result = accuracies.accuracy(data, trials=trials)
            table[name, grouping] = (result.accuracy, result.error)
    return table


def chromatic_accuracy(settings: dict, *, wavelengths=tuple(CALIBRATION_WAVELENGTHS), method: str = "gaussian",
                       half_size: int = 7, batches: int = 4, groups: int = 3, trials: int = 500,
                       modes=CHROMATIC_MODES) -> xr.Dataset:
    """Broadband stars' accuracy on a chromatic detector against the number of calibration wavelengths.

    The bench ``settings`` (:data:`CHROMATIC_BENCH` with a point's overrides) is simulated in memory twice with
    the same seed, hence the same noise draws: as set, and as its achromatic twin (``chromatic.amplitude`` 0,
    the detector at metrology.wavelength at every wavelength). Each is calibrated perfectly
    (:func:`true_calibrations`): the white flat, the offsets at 633 nm, and the chromatic mode from the true
    maps at each number of calibration wavelengths of ``wavelengths`` (keys of :data:`CALIBRATION_WAVELENGTHS`),
    evaluated for the stars' spectrum as the manifest gives it. What is left is what colour does to each
    calibration. ``modes`` (of :data:`CHROMATIC_MODES`) restricts the other modes measured; the scalars whose
    modes are left out are NaN.

    Returns
    -------
    xarray.Dataset
        Per mode (``modes``): ``accuracy_position``, ``error_position``, ``accuracy_group``, ``error_group``
        (Procrustes, pixel) and ``truth_error`` (rms against truth, each position's mean displacement removed,
        pixel). The same per number of calibration wavelengths (dim ``wavelengths``) for the chromatic mode,
        ``chromatic_*``, and ``chromatic_over_achromatic``: its (p) accuracy over the twin's flat+metrology's.
        Scalars: ``gain`` and ``achromatic_gain`` (raw over flat+metrology, (p), on each detector),
        ``photon_limit`` (rms Cramer-Rao bound a position, pixel).
    """
    unknown = [n for n in wavelengths if n not in CALIBRATION_WAVELENGTHS]
    if unknown:
        raise ValueError(f"wavelengths {unknown}: the study knows {sorted(CALIBRATION_WAVELENGTHS)} numbers of "
                         "calibration wavelengths (CALIBRATION_WAVELENGTHS)")
    sets = {n: CALIBRATION_WAVELENGTHS[n] for n in wavelengths}
    twin = apply_overrides(settings, {"chromatic.amplitude": 0.0})
    datasets, errors, configs = {}, {}, {}
    for name, bench in (("", settings), ("achromatic ", twin)):
        cfg, truth, manifest, positions, position_stacks = simulated_stacks(bench, batches=batches,
                                                                            label=f"{name}chromatic")
        if manifest.spectrum is None:
            raise ValueError("the chromatic study's stars need a spectrum (stars.spectrum)")
        configs[name] = cfg
        calibrations = true_calibrations(truth, {} if name else sets, spectrum=(manifest.spectrum.wavelength,
                                                                                manifest.spectrum.weight),
                                         mask=manifest.detector.science_mask())
        calibrations = {mode: c for mode, c in calibrations.items() if mode.startswith("chromatic ")
                        or (name + mode in modes and (not name or mode in ("raw", "flat+metrology")))}
        found, found_errors = _mode_centroids(truth, manifest, positions, position_stacks, calibrations,
                                              method=method, half_size=half_size, label=name + "bench")
        datasets.update({name + mode: ds for mode, ds in found.items()})
        errors.update({name + mode: value for mode, value in found_errors.items()})
    table = _accuracy_table(datasets, groups=groups, trials=trials)
    modes = [m for m in CHROMATIC_MODES if m in modes]
    ds = xr.Dataset(coords={"mode": np.array(modes, dtype=str), "wavelengths": list(sets)})  # (as above)
    for prefix, dim, names in (("", "mode", modes), ("chromatic_", "wavelengths", [f"chromatic {n}" for n in sets])):
        what = "the chromatic mode's " if prefix else ""
        ds[f"{prefix}truth_error"] = ((dim,), [errors[m] for m in names], {
            "units": "pixel", "long_name": f"{what}rms centroid error against truth, each position's mean "
                                           "displacement removed"})
        for grouping in ("position", "group"):
            for k, (field_, text) in enumerate((("accuracy", "corrected Procrustes accuracy"),
                                                ("error", "its 1-sigma error"))):
                ds[f"{prefix}{field_}_{grouping}"] = ((dim,), [table[m, grouping][k] for m in names], {
                    "units": "pixel", "long_name": f"{what}{text} over {grouping}s"})
    p = {m: table[m, "position"][0] if (m, "position") in table else np.nan for m in CHROMATIC_MODES}
    ds["chromatic_over_achromatic"] = (("wavelengths",), [table[f"chromatic {n}", "position"][0]
                                                          / p["achromatic flat+metrology"] for n in sets], {
        "units": "1", "long_name": "the chromatic mode's (p) accuracy over the twin's flat+metrology's"})
    limit = next(iter(datasets.values()))[["photon_limit_x", "photon_limit_y"]].to_array()
    for key, value, what in (
            ("gain", p["raw"] / p["flat+metrology"], "raw over flat+metrology (p), chromatic detector, 633 nm"),
            ("achromatic_gain", p["achromatic raw"] / p["achromatic flat+metrology"],
             "raw over flat+metrology (p), the achromatic twin"),
            ("photon_limit", float(np.sqrt(np.nanmean(limit.values**2))), "rms Cramer-Rao bound a position")):
        ds[key] = ((), value, {"units": "pixel" if key == "photon_limit" else "1", "long_name": what})
    chromatic_cfg = configs[""]
    ds.attrs.update({"method": method, "positions": len(next(iter(datasets.values()))["position"]),
                     "amplitude": float(chromatic_cfg.chromatic.amplitude), "spectrum": chromatic_cfg.stars.spectrum,
                     **{f"calibration_wavelengths_{n}": [float(w) for w in sets[n]] for n in sets}})
    log.info("chromatic amplitude %g, %s stars: gain %.2f (achromatic %.2f); the chromatic mode over the twin's "
             "flat+metrology (p): %s", chromatic_cfg.chromatic.amplitude, chromatic_cfg.stars.spectrum,
             float(ds["gain"]), float(ds["achromatic_gain"]),
             ", ".join(f"{n} wavelength(s) {float(v):.2f}" for n, v in zip(sets, ds["chromatic_over_achromatic"].values)))
    return ds


# --------------------------------------------------------------------------- sweeps

#: Each study's runner: point and settings -> dataset. ``bench`` holds dotted keys of the
#: study's simulated bench, ``options`` its keyword options; a point's parameters are either.
STUDIES = ("offset_bias", "error_propagation", "star_accuracy", "tip_tilt", "stray_light", "chromatic")


def run_point(study: str, point: dict, *, bench: dict | None = None, options: dict | None = None,
              workdir=None) -> xr.Dataset:
    """Run one sweep point of a study.

    Parameters
    ----------
    study : {"offset_bias", "error_propagation", "star_accuracy"}
    point : dict
        The point's parameters: dotted keys of the study's bench (offset_bias:
        :data:`OFFSET_BIAS_BENCH`, e.g. ``detector.prnu_rms``; error_propagation:
        ``star.psf_sigma`` ...; star_accuracy: :data:`STAR_ACCURACY_BENCH`, e.g.
        ``detector.prf_width_spread``) or names of its options (``source``, ``trials``, ``method`` ...).
    bench, options : dict
        The sweep's own settings, under the point's.
    workdir : path, optional
        Where a study may put its temporary simulated files (a temporary folder if not given).
    """
    bench, options = dict(bench or {}), dict(options or {})
    for key, value in point.items():
        value = value.item() if isinstance(value, np.generic) else value
        (bench if "." in key else options)[key] = value
    if study == "offset_bias":
        if workdir is None:
            with tempfile.TemporaryDirectory(prefix="offset-bias-") as folder:
                ds = offset_bias(apply_overrides(OFFSET_BIAS_BENCH, bench), workdir=folder, **options)
        else:
            ds = offset_bias(apply_overrides(OFFSET_BIAS_BENCH, bench), workdir=workdir, **options)
    elif study == "error_propagation":
        stars = {}
        for key, value in bench.items():
            section, _, name = key.partition(".")
            if section != "star":
                raise KeyError(f"{key}: the error_propagation study's bench has only star.* keys")
            stars[name] = value
        ds = error_propagation(star=stars, **options)
    elif study == "star_accuracy":
        ds = star_accuracy(apply_overrides(STAR_ACCURACY_BENCH, bench), **options)
    elif study == "tip_tilt":
        ds = tip_tilt(apply_overrides(TIP_TILT_BENCH, bench), **options)
    elif study == "stray_light":
        with tempfile.TemporaryDirectory(prefix="stray-light-", dir=workdir) as folder:
            ds = stray_light(apply_overrides(STRAY_LIGHT_BENCH, bench), workdir=folder, **options)
    elif study == "chromatic":
        ds = chromatic_accuracy(apply_overrides(CHROMATIC_BENCH, bench), **options)
    else:
        raise ValueError(f"unknown study {study!r}; studies are {', '.join(STUDIES)}")
    ds.attrs.update({"study": study, "point": json.dumps(point)})
    return ds
