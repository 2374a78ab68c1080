"""The workflow end to end on the tiny ``ci`` preset, in a copy of the repository.

The copy carries its own dice_core, first on PYTHONPATH, so that a test can
edit a module and watch which jobs Snakemake would re-run.
"""

import base64
import csv
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
import yaml

from dice_core.calibration import remove_gradient
from dice_core.geometry import two_source_phase
from dice_core.io import read_product, temporary_files, write_cube
from dice_core.manifest import load_manifest

from conftest import REPO, copy_repository, snakemake


def pair_errors_over_floors(offsets, truth):
    """dx and dy of an offsets product against the truth, over their photon floors (rms over rms), once the
    affine part and the product's declared unobservable modes are removed from the truth too."""
    good = np.isfinite(offsets["dx"].values)
    rows, cols = np.nonzero(good)
    n = rows.size
    one, zero, x, y = np.ones(n), np.zeros(n), cols.astype(float), rows.astype(float)
    basis = [np.concatenate(p) for p in [(one, zero), (x, zero), (y, zero), (zero, one), (zero, x), (zero, y)]]
    if "unobservable_dx" in offsets:
        basis += [np.concatenate([mx[good], my[good]]) for mx, my in
                  zip(offsets["unobservable_dx"].values, offsets["unobservable_dy"].values)]
    q, _ = np.linalg.qr(np.array(basis).T)
    true = np.concatenate([truth["dx"].values[good], truth["dy"].values[good]])
    error = np.concatenate([offsets["dx"].values[good], offsets["dy"].values[good]]) - (true - q @ (q.T @ true))
    return tuple(np.sqrt(np.mean(part**2) / np.mean(offsets[f"{name}_photon_noise_floor"].values[good] ** 2))
                 for part, name in ((error[:n], "dx"), (error[n:], "dy")))


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    root = copy_repository(tmp_path_factory.mktemp("workflow"))
    # two worker processes for the jobs that read a baseline in parts, as a large baseline's jobs have
    # (dice_core.resources.reading_workers; the ci preset's are small enough for one): the tests then see
    # the workers' path, and the products do not depend on it
    snakemake(root, "--config", "dataset=ci", "--set-threads", "fit_fringes=2", "allan_deviation=2")
    return root


@pytest.fixture(scope="module")
def out(workdir):
    return workdir / "results" / "sim-ci"


def test_products_and_figures_exist(out):
    for product in ("calibration/dark.nc", "calibration/prnu.nc", "calibration/flats/prnu_fiber_a.nc",
                    "calibration/flats/prnu_fiber_b.nc", "calibration/prnu_difference_fiber_b.nc",
                    "raw/dataset.yaml", "raw/truth.nc"):
        assert (out / product).is_file(), product
    for product in ("metrology/H1H4.nc", "metrology/V2V4.nc", "calibration/offsets_P14.nc",
                    "calibration/offsets_P24.nc", "calibration/offsets_difference_P24.nc", "allan/H1H4.nc",
                    "allan/V2V4.nc", "centroids/raw.nc", "centroids/flat.nc", "centroids/metrology.nc",
                    "centroids/flat+metrology.nc", "calibration/stray_light_H1H4.nc",
                    "calibration/stray_light_V2V4.nc"):
        assert (out / product).is_file(), product
    for figure in ("dark", "dark_noise", "prnu_fiber_a", "prnu_fiber_b", "prnu_difference_fiber_b",
                   "metrology_H1H4", "offsets_P14", "offsets_difference_P24", "allan_H1H4",
                   "centroids_flat+metrology", "procrustes_residuals", "barycentre_residuals",
                   "stray_light_H1H4"):
        for ext in ("png", "pdf"):
            assert (out / "figures" / f"{figure}.{ext}").stat().st_size > 1000, figure
    for log in ("measure_dark", "measure_prnu_fiber_a", "simulate_truth"):
        assert "done" in (out / "logs" / f"{log}.log").read_text()


def test_products_follow_the_contract(out):
    manifest = load_manifest(out / "raw" / "dataset.yaml")
    outside = ~manifest.detector.science_mask()
    dark, prnu = read_product(out / "calibration/dark.nc"), read_product(out / "calibration/prnu.nc")
    assert dark["dark"].attrs["units"] == "adu" and dark["noise"].attrs["units"] == "adu"
    assert prnu["prnu"].attrs["units"] == "1"
    for ds in (dark, prnu):
        for var in ds.data_vars.values():
            assert "units" in var.attrs
        for key in ("dice_core_version", "configuration", "inputs", "history"):
            assert ds.attrs[key]
    for var in (dark["dark"], dark["noise"], prnu["prnu"]):
        assert var.dims == ("row", "col")
        assert np.isnan(var.values[outside]).all() and np.isfinite(var.values[~outside]).all()
    assert np.mean(prnu["prnu"].values[manifest.detector.science_slices]) == pytest.approx(1.0, abs=1e-12)
    assert prnu.attrs["flat"] == "fiber_a"
    assert "dark_000.fits" in dark.attrs["inputs"]


def test_every_coordinate_of_every_product_says_what_it_is(out):
    """A long_name on every coordinate of every netCDF product, and units where it is numeric (a label's values
    are its own words); the two meanings of ``mode`` told apart."""
    found = sorted(out.rglob("*.nc"))
    assert len(found) > 30
    for path in found:
        with xr.open_dataset(path) as ds:
            for name, coord in ds.coords.items():
                assert coord.attrs.get("long_name"), (path, name)
                assert coord.dtype.kind not in "iuf" or coord.attrs.get("units"), (path, name)
    with xr.open_dataset(out / "tables" / "procrustes_residuals.nc") as ds:
        assert ds["mode"].attrs["long_name"].startswith("calibration mode")


def test_products_record_their_code_relative_inputs_with_checksums_and_history(out):
    """Provenance: the hash of the code that made each product, inputs relative to the dataset's and the results
    folders with their sha256, and history appended along the chain of products, CF style."""
    import hashlib
    import json

    dark, prnu = read_product(out / "calibration/dark.nc"), read_product(out / "calibration/prnu.nc")
    centroids = read_product(out / "centroids/raw.nc")
    # the Allan step records the raw files' sha256 the fit took (adopt_stored_digests), not hashed again
    allan = read_product(out / "allan/H1H4.nc")
    fitted = json.loads(read_product(out / "metrology/H1H4.nc").attrs["inputs"])
    files = sum(r["path"].endswith(".fits") for r in fitted)
    assert f"the SHA-256 of {files} of its {files} file(s) taken from the fit's, as it hashed them" in (
        out / "logs/allan_deviation_H1H4.log").read_text()
    for ds in (dark, prnu, centroids, allan):
        assert len(ds.attrs["code_version"]) == 16 and ds.attrs["code_version"] in ds.attrs["history"]
        for record in json.loads(ds.attrs["inputs"]):
            assert record["relative_to"] in ("dataset", "results") and not record["path"].startswith("/")
            root = out / "raw" if record["relative_to"] == "dataset" else out
            assert record["sha256"] == hashlib.sha256((root / record["path"]).read_bytes()).hexdigest()
    assert ("dark/dark_000.fits", "dataset") in [(r["path"], r["relative_to"]) for r in json.loads(dark.attrs["inputs"])]
    assert dark.attrs["code_version"] != centroids.attrs["code_version"]  # each its own step's modules
    # each product's history holds its inputs' history, then its own line last
    assert dark.attrs["history"].splitlines()[-1] in centroids.attrs["history"].splitlines()[:-1]
    assert "raw.nc" in centroids.attrs["history"].splitlines()[-1]
    assert centroids["position"].attrs["units"] == "1" and centroids["star"].attrs["long_name"]
    metrology = read_product(out / "metrology/H1H4.nc")
    assert metrology["frame"].attrs["long_name"] and metrology["iteration"].attrs["units"] == "1"
    assert metrology["masked"].attrs["flag_meanings"] == "measured masked"
    assert metrology["masked"].attrs["flag_values"].tolist() == [0, 1]


def merged(base, update):
    """``update`` merged into ``base``, mapping by mapping, as Snakemake merges configuration files."""
    out = dict(base)
    for key, value in update.items():
        out[key] = merged(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


def ci_config(overrides=None):
    """The configuration a run on the ci preset reads: config/config.yaml with ``overrides`` (a mapping, as a
    configuration file or --config gives it), and the schema's defaults."""
    from dice_core import settings

    values = merged(yaml.safe_load((REPO / "config" / "config.yaml").read_text()), {"dataset": "ci"})
    values = merged(values, overrides or {})
    return settings.with_defaults(values, settings.config_schema(REPO / "workflow" / "schemas" / "config.schema.yaml"))


def configuration_problems(out, config):
    """Each netCDF product under ``out`` (the simulation's truth aside: its configuration is the preset) whose
    ``configuration`` is not exactly its step's settings (dice_core.steps) as ``config`` gives them, or whose
    ``code_version`` or ``inputs`` are missing or absolute; and the number of products read."""
    import json

    from dice_core import products, settings, steps

    problems, count = [], 0
    for path in sorted(out.rglob("*.nc")):
        if path.relative_to(out).parts[0] == "raw":
            continue
        count += 1
        entry, wildcards = products.match(path)
        attrs = xr.open_dataset(path).attrs
        expected = settings.select(config, steps.settings_keys(entry.step), **wildcards)
        if json.loads(attrs.get("configuration", "null")) != json.loads(json.dumps(expected)):
            problems.append(f"{path.relative_to(out)}: configuration {attrs.get('configuration')} is not {expected}")
        if len(attrs.get("code_version", "")) != 16:
            problems.append(f"{path.relative_to(out)}: no code_version")
        if any(r["path"].startswith("/") or r["relative_to"] not in ("dataset", "results")
               for r in json.loads(attrs.get("inputs", "[{}]") or "[{}]")):
            problems.append(f"{path.relative_to(out)}: inputs {attrs.get('inputs')} not relative")
    return problems, count


def test_every_product_records_exactly_its_step_s_settings_its_code_and_relative_inputs(out):
    """Every .nc of the run, not three: its configuration is its step's settings (dice_core.steps) and nothing
    else, with the hash of its code and its inputs relative to the dataset's or the results folder."""
    import json

    problems, count = configuration_problems(out, ci_config())
    assert count >= 30 and problems == []
    truth = xr.open_dataset(out / "raw" / "truth.nc").attrs
    assert len(truth["code_version"]) == 16 and json.loads(truth["inputs"]) == []


@pytest.mark.slow  # 90 s: the PRNU and everything made from it run again (2 idle cores, 2026-12-04): pytest -m slow
def test_after_a_changed_setting_every_product_records_the_configuration_it_was_made_with(workdir, tmp_path):
    """prnu.gradient_degree changed on the command line after a complete run: the PRNU maps of every flat and
    everything made from them are made again, and then every product's configuration is its step's share of
    the new configuration (the issue found one flat's map at the new degree and the other's at the old)."""
    copy = tmp_path / "copy"
    shutil.copytree(workdir, copy, symlinks=True, ignore=shutil.ignore_patterns("__pycache__"))
    snakemake(copy, "--config", "dataset=ci", "prnu={gradient_degree: 2}")
    problems, count = configuration_problems(copy / "results" / "sim-ci", ci_config({"prnu": {"gradient_degree": 2}}))
    assert count >= 30 and problems == []


def test_everything_written_is_readable_as_the_umask_allows(workdir, out):
    """Products, tables, cubes, figures, manifests and logs: 0666 minus the umask, as a plain open gives."""
    umask = os.umask(0)
    os.umask(umask)
    expected = 0o666 & ~umask
    files = [p for p in out.rglob("*") if p.is_file()]
    assert len(files) > 100
    assert {str(p.relative_to(out)): oct(p.stat().st_mode & 0o777) for p in files
            if p.stat().st_mode & 0o777 != expected} == {}


def test_bad_pixel_mask_product(out):
    """The ci preset has no dead or hot pixels; its dust pixels are found, and the flags follow CF."""
    mask = read_product(out / "calibration/bad_pixels.nc")
    assert int(mask["n_dead"]) == int(mask["n_hot"]) == int(mask["n_column"]) == 0
    assert 1 <= int(mask["n_dust"]) <= 12
    assert mask["bad_pixel"].dims == ("row", "col") and mask["bad_pixel"].attrs["flag_meanings"]


def test_prnu_product_matches_truth(out):
    manifest = load_manifest(out / "raw" / "dataset.yaml")
    truth = read_product(out / "raw" / "truth.nc")
    prnu = read_product(out / "calibration/prnu.nc")
    expected, _ = remove_gradient(truth["sensitivity"].values, manifest.detector.science_mask())
    sl = manifest.detector.science_slices
    error = prnu["prnu"].values[sl] - expected[sl] / expected[sl].mean()
    assert np.sqrt(np.mean(error**2)) < 1.5 * float(prnu["photon_noise_limit_rms"])


def test_metrology_products_follow_the_contract_and_the_truth(out):
    manifest = load_manifest(out / "raw" / "dataset.yaml")
    truth = read_product(out / "raw" / "truth.nc")
    outside = ~manifest.detector.science_mask()
    metrology = read_product(out / "metrology/H1H4.nc")
    for name, units in {"projected_offset": "pixel", "iota": "1", "alpha": "1", "kx": "rad/pixel",
                        "ky": "rad/pixel", "phase": "rad"}.items():
        assert metrology[name].attrs["units"] == units, name
    assert metrology["kx"].dims == () and metrology["phase"].dims == ("frame",)
    assert metrology.sizes["frame"] == 300
    assert np.isnan(metrology["projected_offset"].values[outside]).all()
    offsets = read_product(out / "calibration/offsets_P14.nc")
    sl = manifest.detector.science_slices
    for axis in ("dx", "dy"):
        assert offsets[axis].attrs["units"] == "pixel" and offsets[axis].dims == ("row", "col")
        error = offsets[axis].values[sl] - truth[axis].values[sl]
        floor = offsets[f"{axis}_photon_noise_floor"].values[sl]
        # the truth has no affine part, the product none by construction: compare directly
        assert np.sqrt(np.mean(error**2)) < 1.2 * np.sqrt(np.mean(floor**2)), axis
    difference = read_product(out / "calibration/offsets_difference_P24.nc")
    assert float(difference["ddx_std"]) < 1.3 * float(difference["ddx_photon_noise_floor"])


def test_the_ci_bench_shows_no_stray_light_and_the_logs_say_so(out):
    """The ci bench has none (metrology.stray_light: detect by default): no baseline and neither component of
    the pair difference shows a component, each product holds its spectrum, and each log says it in a line."""
    for baseline in ("H1H4", "V1V4", "H2H4", "V2V4"):
        stray = read_product(out / f"calibration/stray_light_{baseline}.nc")
        assert int(stray["n_components"]) == 0 and stray.sizes["component"] == 0, baseline
        assert stray["power"].dims == ("frequency_y", "frequency_x") and float(stray["false_alarm"]) == 1e-3
        assert float(stray["white_level"]) > 0 and np.nanmax(stray["power"].values) < float(stray["threshold"]) * 2
        assert f"{baseline}: no coherent stray light" in (out / f"logs/find_stray_light_{baseline}.log").read_text()
    difference = read_product(out / "calibration/offsets_difference_P24.nc")
    assert int(difference["ddx_n_components"]) == 0 and int(difference["ddy_n_components"]) == 0
    assert "ddy of P24 - P14: no coherent stray light" in (out / "logs/compare_pairs_P24.log").read_text()


@pytest.mark.parametrize("step", ["fit_fringes_H1H4", "allan_deviation_H1H4"])
def test_steps_run_one_blas_thread_per_worker_whatever_snakemake_sets(out, step):
    """Snakemake sets the thread variables to a rule's threads (2); each process still runs one BLAS thread."""
    log = (out / "logs" / f"{step}.log").read_text()
    assert "OPENBLAS_NUM_THREADS=2" in log  # what Snakemake asked for
    assert "BLAS threads: 1 in this process, 1, 1 in the processes that read the parts" in log
    assert "in 2 process(es)" in log


def test_allan_product_follows_the_contract(out):
    manifest = load_manifest(out / "raw" / "dataset.yaml")
    outside = ~manifest.detector.science_mask()
    ds = read_product(out / "allan/H1H4.nc")
    assert ds["n_frames"].dims == ("n_frames",) and np.all(np.diff(ds["n_frames"].values) > 0)
    for name in ("deviation", "allan_deviation"):
        assert ds[name].dims == ("n_frames", "row", "col") and ds[name].attrs["units"] == "pixel"
        assert np.isnan(ds[name].values[:, outside]).all()
    for name in ("deviation_mean", "allan_deviation_mean", "photon_limit_pixel", "photon_limit_block"):
        assert ds[name].dims == ("n_frames",) and ds[name].attrs["units"] == "pixel"
    # 300 frames of the ci preset: photon-limited and white, within the scatter of a few batches
    assert float(ds["slope_batch_means"]) == pytest.approx(-0.5, abs=0.15)
    np.testing.assert_allclose(ds["deviation_mean"], ds["photon_limit_pixel"], rtol=0.25)


def test_prf_widths_follow_the_contract_and_the_truth(out):
    """calibration/prf.nc: each pixel's width along x and y within its stated errors of the truth, the smooth
    part of both (the visibility's, which the contrast cannot see) taken out, the scale of the deviations and
    the mean width within theirs (docs/centroids.md; tests/test_prf.py's checks)."""
    from types import SimpleNamespace

    from test_prf import assert_true_to_the_widths

    truth = read_product(out / "raw" / "truth.nc")
    ds = read_product(out / "calibration" / "prf.nc")
    maps = SimpleNamespace(smooth_degree=ds.attrs["smooth_degree"], mean_width={}, error_mean_width={},
                           error_scale={})
    for axis in "xy":
        for name in ("width", "error_width", "error_width_pixel", "photon_error_width"):
            assert ds[f"{name}_{axis}"].dims == ("row", "col") and ds[f"{name}_{axis}"].attrs["units"] == "pixel"
            setattr(maps, f"{name}_{axis}", ds[f"{name}_{axis}"].values)
        maps.mean_width[axis], maps.error_mean_width[axis] = (float(ds[f"{name}_{axis}"])
                                                              for name in ("mean_width", "error_mean_width"))
        maps.error_scale[axis] = float(ds[f"error_deviation_scale_{axis}"])
        assert assert_true_to_the_widths(maps, truth, axis)["n"] > 1000
    assert "metrology/H1H4.nc" in ds.attrs["inputs"]


def test_centroid_products_follow_the_contract_and_the_truth(out):
    truth = read_product(out / "raw" / "truth.nc")
    errors = {}
    for mode in ("raw", "flat", "metrology", "flat+metrology"):
        ds = read_product(out / "centroids" / f"{mode}.nc")
        for axis in ("x", "y"):
            assert ds[axis].dims == ("position", "star") and ds[axis].attrs["units"] == "pixel"
        assert ds.attrs["mode"] == mode and ds.sizes["star"] == truth.sizes["star"]
        # against truth, each position's common translation removed (differential astrometry)
        e = np.stack([ds["x"].values - truth["star_x"].values, ds["y"].values - truth["star_y"].values])
        errors[mode] = np.sqrt(np.mean(np.square(e - e.mean(axis=2, keepdims=True))))
    assert errors["flat+metrology"] < errors["raw"]


@pytest.mark.parametrize("method", ["fourier", "gaussian"])
def test_every_method_finds_every_star_against_truth(out, method):
    """Per star, each position's common translation removed: the photon bound is about 3e-4 pixel and the
    PRNU's pattern in raw mode about 2e-3; a method fooled by the windows was 0.1-0.6 pixel off (issue 10)."""
    truth = read_product(out / "raw" / "truth.nc")
    folder = out / "centroids" if method == "fourier" else out / "centroids" / method
    for mode in ("raw", "flat", "metrology", "flat+metrology"):
        ds = read_product(folder / f"{mode}.nc")
        assert ds.attrs["method"] == method
        e = np.stack([ds["x"].values - truth["star_x"].values, ds["y"].values - truth["star_y"].values])
        per_star = np.sqrt(np.mean(np.square(e - e.mean(axis=2, keepdims=True)), axis=(0, 1)))
        assert np.all(per_star < 4e-3), (mode, per_star)
        # read from the positions' stacks, never from the cubes again
        inputs = ds.attrs["inputs"]
        assert "stars/1.nc" in inputs and ".fits" not in inputs


def read_accuracy_table(path):
    import csv

    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_accuracy_table_follows_the_contract(out):
    rows = read_accuracy_table(out / "tables" / "accuracy.csv")
    assert {"flat", "metrology", "grouping", "accuracy", "error"} <= set(rows[0])
    from dice_core.centroids import MODES, mode_needs

    # the configured sweep: one row per mode and grouping; every mode but the chromatic one, which needs a
    # calibration across wavelength that ci (one laser, no stated wavelength) has not
    expected = sorted((m, g) for m in MODES if "chromatic" not in mode_needs(m) for g in ("position", "group"))
    for method in ("fourier", "gaussian"):
        assert sorted((r["mode"], r["grouping"]) for r in rows if r["method"] == method) == expected
    for r in rows:  # the flat and metrology columns say what the mode corrects with
        needs = mode_needs(r["mode"])
        assert (r["flat"], r["metrology"]) == (str("flat" in needs).lower(), str("offsets" in needs).lower())
    assert (out / "centroids" / "gaussian" / "flat+metrology.nc").is_file()
    assert all(float(r["accuracy"]) > 0 and float(r["error"]) > 0 for r in rows)
    assert "\\begin{tabular}" in (out / "tables" / "accuracy.tex").read_text()


# 1-2 min on 2 cores, most of it Procrustes's dense fallback on ci's 3-4 alike configurations, run once per
# model; the library's accuracy_tables with every model is in the CI set (tests/test_accuracies.py)
@pytest.mark.slow
def test_every_configured_superimposition_has_its_rows_factors_and_figure(workdir, tmp_path):
    """astrometry.superimposition as a list: the table gains each model's rows with its own Monte Carlo
    deflation factors and error bars, each model its residual product and figure, and the pose its
    identifiability report in the log. Run in a copy, so that the module's table keeps Procrustes alone."""
    copy = tmp_path / "models"
    shutil.copytree(workdir, copy, symlinks=True)
    models = {"astrometry": {"superimposition": ["projective", "pose"], "trials": 100},
              "centroids": {"methods": ["fourier"]}}
    (copy / "models.yaml").write_text(yaml.safe_dump(models))
    out = copy / "results" / "sim-ci"
    run = snakemake(copy, "--config", "dataset=ci", "--configfile", "models.yaml", "--",
                    *(str(out.relative_to(copy) / "figures" / f"{model}_residuals.png")
                      for model in ("procrustes", "projective", "pose")))
    ran = run.stdout + run.stderr
    assert "rule measure_centroids" not in ran and "rule fit_fringes" not in ran  # the table's inputs stand
    rows = read_accuracy_table(out / "tables" / "accuracy.csv")
    by_model = {model: {(r["method"], r["mode"], r["grouping"]): r for r in rows if r["superimposition"] == model}
                for model in ("procrustes", "projective", "pose")}
    assert set(by_model["projective"]) == set(by_model["pose"]) == set(by_model["procrustes"]) != set()
    for key, procrustes in by_model["procrustes"].items():
        for model in ("projective", "pose"):
            row = by_model[model][key]
            assert float(row["accuracy"]) > 0 and float(row["error"]) > 0
            # each model's own deflation factor: more parameters per position, a larger factor
            assert float(row["factor"]) != float(procrustes["factor"])
    for model in ("projective", "pose"):
        residuals = read_product(out / "tables" / f"{model}_residuals.nc")
        assert residuals.attrs["superimposition"] == model
        assert (out / "figures" / f"{model}_residuals.png").stat().st_size > 10_000
    log = (out / "logs" / "accuracy_table.log").read_text()
    # ci's 4 positions and small tip-tilt cannot identify the pose: said, and no pose accuracy claimed
    assert "no pose accuracy reported" in log


@pytest.mark.slow  # 71 s: a rerun of one centroid mode and its table (2 idle cores, 2026-12-02): pytest -m slow
def test_a_mode_added_to_the_sweep_runs_only_its_own_jobs(workdir, out):
    """Snakemake's own up-to-date logic: the other modes' centroids are not redone."""
    (workdir / "fewer.yaml").write_text("centroids:\n  modes: [raw, flat, metrology]\n  methods: [fourier]\n")
    plan = snakemake(workdir, "-n", "--config", "dataset=ci", "--configfile", "fewer.yaml").stdout
    assert "measure_centroids" not in plan and "accuracy_table" in plan  # the table gathers a new list
    (out / "centroids" / "metrology.nc").unlink()  # as if metrology had just been added to the list
    run = snakemake(workdir, "--config", "dataset=ci")
    ran = run.stdout + run.stderr
    assert ran.count("rule measure_centroids:") == 1 and "wildcards: mode=metrology" in ran
    assert "rule accuracy_table:" in ran
    assert (out / "centroids" / "metrology.nc").is_file()


def test_inputs_cut_into_other_jobs_make_the_same_stacks_and_simulate_nothing_again(workdir, out, tmp_path):
    """job_samples cuts the simulated files and the star positions into jobs, a simulation job never holding
    two acquisitions' files but the positions'. The ci preset's 4 positions (40x44 pixels x 4 frames, 7040
    samples each) are one job by default. With 15,000 samples a job the dark, the flats and the metrology files
    are each a job of their own, and the positions' files and stacks two jobs of two. On the complete run this re-stacks and re-runs what reads the stacks, and simulates
    nothing again; stacked anew from the same raw files into another folder, each position's stack holds the one
    job's values exactly."""
    from dice_core import steps

    per_two = "job_samples=15000"
    plan = plans_of(workdir, ["--config", "dataset=ci", per_two])[0]
    planned = {rule for rule, _ in plan}
    assert {r for r in planned if r.startswith("stack_position")} == {"stack_position_1_to_2", "stack_position_3_to_4"}
    assert not {steps.step_of_rule(r) for r in planned} & {"simulate_file", "simulate_truth", "fit_fringes"}
    listed = set(snakemake(workdir, "--list-rules", "--config", "dataset=ci", per_two).stdout.split())
    assert {f"simulate_file_{n}" for n in range(1, 12)} | {"simulate_file_12_to_13", "simulate_file_14_to_15"} == {
        r for r in listed if r.startswith("simulate_file")}
    # the default: a job for each of the dark and the flats, one for each baseline's two files, one for the
    # positions' files, and one for their stacks
    assert {"simulate_file_1", "simulate_file_4_to_5", "simulate_file_10_to_11", "simulate_file_12_to_15",
            "stack_position_1_to_4"} <= rules_of(workdir)

    other = tmp_path / "results"
    stacks = [f"{other}/sim-ci/stars/{index}.nc" for index in range(1, 5)]
    ran = snakemake(workdir, *stacks, "--config", "dataset=ci", f"raw={out / 'raw'}", f"results={other}", per_two)
    ran_rules = re.findall(r"^(?:local)?rule (\w+):", ran.stdout + ran.stderr, re.M)
    assert sorted(ran_rules) == ["stack_position_1_to_2", "stack_position_3_to_4"], ran_rules
    for index, path in enumerate(stacks, start=1):
        with xr.open_dataset(path) as regrouped, xr.open_dataset(out / "stars" / f"{index}.nc") as one_job:
            assert regrouped.attrs["position"] == index
            xr.testing.assert_identical(regrouped.drop_attrs(), one_job.drop_attrs())


# A valid value other than the default of every key of the configuration that a step reads, for the ci preset
# (dice_core.steps.PLANNING_KEYS choose what is made, not how: they are not in it).
OTHER_VALUES = {
    "chunk_frames": 16, "prnu.gradient_degree": 2, "metrology.tolerance": 2.0e-7, "metrology.max_passes": 9,
    "metrology.parts": 3, "metrology.use_flat": False, "metrology.smooth_degree": 5, "metrology.tip_sigma": 2.0e-3,
    "metrology.stray_light": "remove",
    "prf.order": 6.0, "prf.half_width": 0.45, "prf.sigma": 0.32, "centroids.modes": ["raw", "flat"],
    "centroids.method": "gaussian", "centroids.methods": ["fourier"], "centroids.half_size": 6,
    "centroids.batches": 3, "centroids.pair": "P24", "centroids.spectrum": "warm", "astrometry.positions": [1, 3],
    "astrometry.groups": 2,
    "astrometry.trials": 1000, "astrometry.superimposition": "projective", "astrometry.pose.distance": 30000.0,
    "astrometry.pose.off_axis_deg": 3.0, "astrometry.pose.centre": [20.0, 20.0],
    "paper.offset_bias": "offset_bias_causes", "paper.error_propagation": "error_propagation_sources",
    "paper.stray_light": "stray_light_small",
    "paper.chromatic": "chromatic_cool",
}
# the second error_propagation, stray_light and chromatic sweeps paper.error_propagation, paper.stray_light
# and paper.chromatic may name
EXTRA_SWEEP = {"sweeps": {"error_propagation_sources": {"study": "error_propagation", "parameter": "source",
                                                        "values": ["prnu", "read"], "options": {"trials": 50}},
                          "stray_light_small": {"study": "stray_light", "parameter": "stray_light.field_ratio",
                                                "values": [1.0e-3], "bench": {"metrology.frames": 300}},
                          "chromatic_cool": {"study": "chromatic", "parameter": "stars.spectrum", "values": ["cool"]}}}


def nested(key, value):
    """{a: {b: value}} for the dotted key a.b."""
    for part in reversed(key.split(".")):
        value = {part: value}
    return value


def command_line(key, value):
    """The README's way to set a nested key on the command line: ``--config 'section={key: value}'``, a YAML
    mapping whose values the schema types."""
    section, *rest = key.split(".")
    inner = nested(".".join(rest), value)[rest[0]] if rest else value
    text = yaml.safe_dump({rest[0]: inner} if rest else inner, default_flow_style=True, width=1000).strip()
    return f"{section}={text.removesuffix('...').strip()}"


def planned_jobs(plan, rule=r"\w+"):
    """The jobs of a dry run's output, ``[(rule, its block of lines)]``, of the rules the pattern ``rule``
    matches."""
    return re.findall(rf"^(?:local)?rule ({rule}):\n(.*?)(?=^\S|\Z)", plan, re.M | re.S)


def plans_of(workdir, *arg_lists):
    """The jobs each dry run plans, ``{(rule, its outputs): Snakemake's reason}`` (the target rules aside), the
    runs two at a time: one dry run per list of arguments."""
    env = {**os.environ, "PYTHONPATH": str(workdir)}
    runs = [subprocess.Popen([sys.executable, "-m", "snakemake", "--cores", "2", "-n", *args], cwd=workdir, env=env,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for args in arg_lists]
    plans = []
    for run, args in zip(runs, arg_lists):
        out, err = run.communicate(timeout=600)
        assert run.returncode == 0, (args, out[-2000:], err[-2000:])
        jobs = planned_jobs(out)
        plans.append({(rule, re.search(r"^\s+output: (.*)$", block, re.M).group(1)): reason_of(block)
                      for rule, block in jobs if rule not in ("all", "paper")})
    return plans


def reason_of(block):
    """Snakemake's reason for a planned job, from its block of a dry run's output."""
    found = re.search(r"^\s+reason: (.*)$", block, re.M)
    return found.group(1) if found else ""


def rules_of(workdir):
    """The rules of the workflow on the ci preset."""
    listed = snakemake(workdir, "--list-rules", "--config", "dataset=ci").stdout.split()
    return set(listed)


def has_jobs_on(name, dataset="ci"):
    """Whether step ``name`` has jobs in preset ``dataset``'s default target: a step whose products all lack wildcards
    has one only where the plan makes them (calibration/chromatic.nc: datasets of several wavelengths)."""
    from dice_core import planning, products, settings, steps

    schema = settings.config_schema(REPO / "workflow" / "schemas" / "config.schema.yaml")
    config = settings.with_defaults({**yaml.safe_load((REPO / "config" / "config.yaml").read_text()),
                                     "dataset": dataset}, schema)
    manifest, _ = planning.load_dataset(dataset, presets=REPO / "config" / "presets", results="results")
    targets = set(planning.Plan(manifest, config, f"results/sim-{dataset}", "results/sweeps").default_targets())
    written = [products.entry(key) for key in steps.step(name).writes]
    return any(p.wildcards for p in written) or any(
        products.path_of(p.key, dataset_root=f"results/sim-{dataset}", sweeps_root="results/sweeps",
                         suffix=".png" if p.kind == "figure" else "") in targets for p in written)


def check_key_triggers_its_steps(workdir, key, tmp_path, configfile=None, dataset="ci"):
    """After a complete run, ``key`` set to another value on the command line plans exactly the steps that
    declare it (dice_core.steps) and what follows from them, for the default target and for those steps' own
    products: the same jobs as a run that forces those steps, and no job re-run for its parameters but theirs.
    ``configfile``: more configuration, as the complete run had it (the paper's sweeps); ``dataset``: the
    preset the complete run reduced."""
    from dice_core import products, steps

    rules = rules_of(workdir)  # the split fit's steps are rules only with metrology.split
    # the rules of the steps that declare the key (a step of the star positions has a rule per group of them)
    declaring = [rule for rule in sorted(rules - {"all", "paper"})
                 if key in steps.settings_keys(steps.step_of_rule(rule))]
    extra = tmp_path / "more.yaml"
    extra.write_text(yaml.safe_dump(merged(EXTRA_SWEEP, configfile or {})))
    args = ["--configfile", str(extra), "--config", f"dataset={dataset}", command_line(key, OTHER_VALUES[key])]

    def same_plans(natural, forced_plan, what):
        assert natural.keys() == forced_plan.keys(), (key, what, set(natural) ^ set(forced_plan))
        # a job re-run for its parameters or its code is one of the declaring steps' (the forced plan holds every
        # job that follows from them too, so the comparison alone would not see another step re-run by the key)
        rerun = {job for job, reason in natural.items() if "Params have changed" in reason or "Code has" in reason}
        assert {rule for rule, _ in rerun} <= set(declaring), (key, what, rerun)

    # the default target's steps: forcing a step of the run as a whole (the paper's), or one this dataset has no
    # job of (calibration/chromatic.nc on a single wavelength), would add it to the plan
    in_default = [rule for rule in declaring if not steps.step(steps.step_of_rule(rule)).whole_run
                  and has_jobs_on(steps.step_of_rule(rule), dataset)]
    natural, forced_plan = plans_of(workdir, args, [*args, *(["--forcerun", *in_default] if in_default else [])])
    same_plans(natural, forced_plan, "default target")
    forced = ["--forcerun", *declaring] if declaring else []
    own = sorted({out for (rule, outputs) in forced_plan if rule in declaring for out in outputs.split(", ")} | {
        products.path_of(p, dataset_root=f"results/sim-{dataset}", sweeps_root="results/sweeps",
                         suffix=".png" if products.entry(p).kind == "figure" else "")
        for rule in declaring for p in steps.step(steps.step_of_rule(rule)).writes if not products.entry(p).wildcards})
    if own:
        natural, forced_plan = plans_of(workdir, [*own, *args], [*own, *args, *forced])
        same_plans(natural, forced_plan, "own products")
        assert {rule for rule, _ in natural} & set(declaring), (key, natural)  # the step itself is planned
    return natural


# the two the issue found planning nothing (each 20-25 s: four dry runs, two at a time); the others are in the
# slow test below
TRIGGER_KEYS_IN_CI = ["prnu.gradient_degree", "astrometry.superimposition"]


@pytest.mark.parametrize("key", TRIGGER_KEYS_IN_CI)
def test_a_changed_setting_reruns_exactly_the_steps_that_read_it(workdir, key, tmp_path):
    check_key_triggers_its_steps(workdir, key, tmp_path)


def test_every_key_a_step_reads_has_a_value_for_the_trigger_test():
    """A key added to the schema tomorrow is named here until the trigger test can set it."""
    from dice_core import settings, steps

    leaves = settings.leaf_keys(settings.config_schema(REPO / "workflow" / "schemas" / "config.schema.yaml"))
    assert sorted(OTHER_VALUES) == sorted(k for k in leaves if k not in steps.PLANNING_KEYS)


@pytest.mark.slow  # 4 dry runs a key, two at a time: about 10 min on 2 shared cores (2026-12-04): pytest -m slow
def test_every_key_of_the_schema_reruns_exactly_the_steps_that_read_it(workdir, paper_run, tmp_path):
    """For every key of the configuration's schema that a step reads, from the step table, after the default
    and the paper targets have run (so that the paper's steps' own products exist to be re-made)."""
    for key in OTHER_VALUES:
        check_key_triggers_its_steps(workdir, key, tmp_path, configfile=PAPER_CI)


def rules_planned_after_editing(workdir, module_name, *target):
    """The rules a dry run plans once ``dice_core/<module_name>.py`` is edited (the edit then undone), the
    workflow being up to date before and after (``target``: a target and its options, the default target's
    on the ci preset if none)."""
    target = target or ("--config", "dataset=ci")
    assert "Nothing to be done" in snakemake(workdir, "-n", *target).stdout
    module = workdir / "dice_core" / f"{module_name}.py"
    original = module.read_text()
    try:
        module.write_text(original + "\n# a change to the module\n")
        plan = snakemake(workdir, "-n", *target).stdout
    finally:
        module.write_text(original)
    assert "Nothing to be done" in snakemake(workdir, "-n", *target).stdout
    return {line.split()[1].rstrip(":") for line in plan.splitlines() if line.startswith(("rule ", "localrule "))}


@pytest.mark.slow  # 37 s; the indirect-import case below stays in the CI set (2 idle cores, 2026-12-02): pytest -m slow
def test_up_to_date_then_dice_core_change_reruns_what_it_affects(workdir):
    rules = rules_planned_after_editing(workdir, "calibration")
    assert {"measure_dark", "measure_prnu", "compare_prnu"} <= rules
    assert not any(r.startswith("simulate") for r in rules)


def test_a_module_change_reruns_the_steps_that_import_it_through_another(workdir):
    """The plot steps name only plotting and io; io imports manifest: editing manifest re-runs them too."""
    assert {"plot_dark", "plot_metrology", "fit_fringes"} <= rules_planned_after_editing(workdir, "manifest")


def test_lint_has_nothing_to_say(workdir):
    result = snakemake(workdir, "--lint", "--config", "dataset=ci")
    assert "Lints for" not in result.stdout + result.stderr


def test_rule_files_are_formatted_by_snakefmt():
    """CI's `snakefmt --check`, with the repository's settings (pyproject.toml, [tool.snakefmt])."""
    result = subprocess.run([sys.executable, "-m", "snakefmt", "--check", "Snakefile", "workflow"], cwd=REPO,
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr


def incomplete_outputs(root):
    """Outputs on disk that Snakemake still marks incomplete: their job started and was not seen to end."""
    found = []
    for marker in (root / ".snakemake" / "incomplete").rglob("*"):
        try:
            path = base64.urlsafe_b64decode(marker.name).decode()
        except ValueError:  # not a marker (migration_underway)
            continue
        if marker.is_file() and (root / path).is_file():
            found.append(path)
    return found


def snakemake_locks(root):
    return sorted((root / ".snakemake" / "locks").glob("*.lock"))


@pytest.mark.slow  # a whole workflow run or more (4 min on 2 shared cores): pytest -m slow
def test_a_killed_run_is_finished_by_running_the_same_command_again(out, tmp_path):
    """kill -9 of Snakemake and its jobs leaves an output marked incomplete and Snakemake's lock; the same
    command, run again once, finishes the run (docs/running.md, "After a crash") with the uninterrupted run's products.
    While the run is alive, its lock still keeps a second run out."""
    root = copy_repository(tmp_path)
    args = ("--config", "dataset=ci")
    run = subprocess.Popen([sys.executable, "-m", "snakemake", "--cores", "2", *args], cwd=root,
                           env={**os.environ, "PYTHONPATH": str(root)}, stdout=subprocess.DEVNULL,
                           stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        deadline = time.monotonic() + 300
        while not snakemake_locks(root):
            assert run.poll() is None and time.monotonic() < deadline, "the run took no lock"
            time.sleep(0.05)
        second = snakemake(root, *args, check=False)
        said = second.stdout + second.stderr
        assert second.returncode != 0 and f"another run of this workflow is alive in this folder (pid {run.pid}, " \
            in said and "do not use --unlock" in said and "--unlock argument" not in said, said
        assert run.poll() is None and snakemake_locks(root)  # refused while the first was alive; lock kept
        # kill in the window between a job's output appearing and Snakemake recording the job as done,
        # the run frozen (SIGSTOP) to make sure it is still in that window
        while True:
            assert run.poll() is None and time.monotonic() < deadline, "no job was caught before its end"
            if incomplete_outputs(root):
                os.killpg(run.pid, signal.SIGSTOP)
                if incomplete_outputs(root):
                    break
                os.killpg(run.pid, signal.SIGCONT)
            time.sleep(0.01)
    finally:
        os.killpg(run.pid, signal.SIGKILL)  # Snakemake and its jobs, as kill -9 of a process group
        run.wait()
    killed_during = incomplete_outputs(root)
    assert killed_during and snakemake_locks(root)
    # what a writer killed between creating its temporary file and renaming it leaves (the kill above may
    # not have caught one), beside an output of the run and beside a file that is not one
    figures = root / "results" / "sim-ci" / "figures"
    figures.mkdir(parents=True, exist_ok=True)
    left = [figures / ".metrology_H1H4.png.0123456789ab.part", *temporary_files(root / "results")]
    foreign = figures / ".notes.txt.0123456789ab.part"
    for path in (left[0], foreign):
        path.write_bytes(b"")

    again = snakemake(root, *args)  # the README's command, as it was
    said = again.stdout + again.stderr
    assert "removed the lock of a run" in said
    assert f"removed {len(set(left))} temporary file(s) left by a run that was cut short" in said
    assert temporary_files(root / "results") == [foreign]  # not a temporary file of this run's: left alone
    assert "IncompleteFilesException" not in said and "cannot be locked" not in said
    assert all(path in said for path in killed_during)  # the jobs cut short ran again ("Forced execution")
    assert not incomplete_outputs(root) and not snakemake_locks(root)
    ours, theirs = root / "results" / "sim-ci", out
    products = sorted(p.relative_to(ours) for p in ours.rglob("*") if p.suffix in (".nc", ".fits", ".csv"))
    assert len(products) > 40
    for product in products:
        if product.suffix == ".nc":
            xr.testing.assert_equal(read_product(ours / product), read_product(theirs / product))
        else:
            assert (ours / product).read_bytes() == (theirs / product).read_bytes(), product


# 25 s; the lock's removal logic runs in every workflow run of the CI set
@pytest.mark.slow  # (2 idle cores, 2026-12-02): pytest -m slow
def test_a_stale_lock_is_removed_only_when_its_run_was_on_this_machine(tmp_path):
    """A run elsewhere on a shared folder may be alive without this machine seeing its flock: its lock stays
    (Snakemake then asks for --unlock). A lock left by a run of this machine goes."""
    root = copy_repository(tmp_path)
    lock, guard = root / ".snakemake" / "locks" / "0.output.lock", root / ".snakemake" / "dice" / "running"
    lock.parent.mkdir(parents=True)
    guard.parent.mkdir(parents=True)
    lock.write_text("results/sim-ci/raw/truth.nc\n")
    guard.write_text("another-machine\n")
    said = snakemake(root, "-n", "--config", "dataset=ci").stderr
    assert lock.is_file() and "removed the lock" not in said and guard.read_text() == "another-machine\n"
    guard.write_text(socket.gethostname() + "\n")
    said = snakemake(root, "-n", "--config", "dataset=ci").stderr
    assert not lock.exists() and "removed the lock of a run" in said


def within_what_it_asked(workdir, rule, block, asked):
    """Whether a planned job (its rule and block of Snakemake's output) has a benchmark; if so, assert that
    its measured memory and time are within the ``asked`` mem_mb (less the executor's) and runtime."""
    from dice_core import resources

    benchmark = re.search(r"^\s+benchmark: (\S+)", block, re.M)
    if not benchmark:
        return False
    with open(workdir / benchmark.group(1)) as handle:
        measured = next(csv.DictReader(handle, delimiter="\t"))
    assert float(measured["max_rss"]) <= int(asked["mem_mb"]) - resources.EXECUTOR_MB, (rule, measured)
    assert float(measured["s"]) <= 60 * int(asked["runtime"]), (rule, measured)
    return True


def test_every_job_asks_for_memory_and_time_that_cover_what_its_benchmark_measured(workdir):
    """Each job's mem_mb and runtime (dice_core.resources, from the dataset's size) are in the plan, and cover
    the peak memory and the wall time its benchmark file measured in this run (the request less the
    Snakemake process that runs the job on a cluster node)."""
    plan = snakemake(workdir, "-n", "--forceall", "--config", "dataset=ci").stdout
    jobs = planned_jobs(plan)
    checked = 0
    for rule, block in jobs:
        if rule == "all":
            continue
        asked = dict(re.findall(r"\b(mem_mb|runtime)=(\d+)", block))
        assert set(asked) == {"mem_mb", "runtime"}, (rule, block)
        checked += within_what_it_asked(workdir, rule, block, asked)
    assert checked >= 20  # the simulation's files, dark, flats, fits, Allan, stacks, centroids


def test_only_a_large_baseline_s_fit_and_allan_jobs_ask_for_two_threads_with_cores_to_spare(workdir):
    """The rules' threads (dice_core.resources.reading_workers): the paper preset's baselines (1.3e9 samples in
    10 files) ask for two, one per part, where the run's cores give each of its four baselines two (--cores 8),
    and for one on the README's 2 cores; the ci preset's (2e6 samples) for one, in each of the 8 jobs. A
    cluster job's own Snakemake (--mode remote, its slot's cores) keeps the two it was submitted with."""
    for dataset, cores, mode, threads in (("paper", 8, (), "2"), ("paper", 2, (), None), ("ci", 8, (), None),
                                          ("paper", 2, ("--mode", "remote"), "2")):
        plan = snakemake(workdir, "-n", "--forceall", *mode, "--config", f"dataset={dataset}", cores=cores).stdout
        jobs = planned_jobs(plan)
        asked = [re.search(r"^\s+threads: (\d+)", block, re.M) for rule, block in jobs
                 if rule in ("fit_fringes", "allan_deviation")]
        assert [found.group(1) if found else None for found in asked] == [threads] * 8, (dataset, cores, mode)


def test_an_allan_job_asks_for_the_memory_of_the_workers_it_runs(workdir):
    """The resources follow the job's threads as Snakemake gives them: --set-threads allan_deviation=2 on 2
    cores asks each Allan job for its second worker's memory too (dice_core.resources.job_data's workers)."""
    def allan_mem_mb(*args):
        plan = snakemake(workdir, "-n", "--forceall", "--config", "dataset=paper", *args).stdout
        jobs = planned_jobs(plan)
        return {int(re.search(r"mem_mb=(\d+)", block).group(1)) for rule, block in jobs if rule == "allan_deviation"}

    one, two = allan_mem_mb(), allan_mem_mb("--set-threads", "allan_deviation=2")
    assert len(one) == len(two) == 1 and min(two) > max(one), (one, two)


def test_missing_manifest_is_a_clear_error(workdir, tmp_path):
    missing = tmp_path / "nowhere" / "dataset.yaml"
    result = snakemake(workdir, "-n", "--config", f"dataset={missing}", check=False)
    said = result.stdout + result.stderr  # Snakemake 9 reports workflow errors on stdout
    assert result.returncode != 0
    assert f"{missing}: manifest not found" in said


def test_a_mistyped_config_key_is_named_with_the_nearest_valid_key(workdir):
    (workdir / "typo.yaml").write_text("centroids:\n  half_sise: 4\nastrometry:\n  groups: many\n")
    result = snakemake(workdir, "-n", "--config", "dataset=ci", "--configfile", "typo.yaml", check=False)
    said = result.stdout + result.stderr
    assert result.returncode != 0
    assert "config centroids.half_sise: unknown key; did you mean centroids.half_size?" in said
    assert "config astrometry.groups: 'many' is not of type 'integer'" in said
    assert len(said.splitlines()) < 25 and "additionalProperties" not in said  # not the schema in full


def test_the_readme_s_command_line_form_sets_nested_keys_typed_and_checked(workdir):
    """docs/running.md, "Settings": --config 'section={key: value}' (Snakemake reads its values as strings; the
    schema types them), a misspelt key named with the nearest valid one, in one line each."""
    readme = (REPO / "docs" / "running.md").read_text()
    assert "--config 'centroids={method: gaussian, half_size: 6}' chunk_frames=16" in readme
    plan = snakemake(workdir, "-n", "--config", "dataset=ci", "centroids={method: gaussian, half_size: 6}",
                     "chunk_frames=16").stdout
    assert "rule measure_centroids:" in plan and "rule measure_dark:" in plan
    result = snakemake(workdir, "-n", "--config", "dataset=ci", "centroids={half_sise: 4}", "prnu={gradient_degree: x}",
                       check=False)
    said = result.stdout + result.stderr
    schema = yaml.safe_load((REPO / "workflow" / "schemas" / "config.schema.yaml").read_text())
    keys = ", ".join(schema["properties"]["centroids"]["properties"])  # in the schema's order
    assert result.returncode == 1 and [line for line in said.splitlines() if line.startswith("dice: ")] == [
        f"dice: config centroids.half_sise: unknown key; did you mean centroids.half_size? (keys of centroids: {keys})",
        "dice: config prnu.gradient_degree: 'x' is not of type 'integer'"], said


def test_unknown_preset_is_a_clear_error(workdir):
    result = snakemake(workdir, "-n", "--config", "dataset=nopreset", check=False)
    assert result.returncode != 0
    assert "neither a manifest path" in result.stdout + result.stderr


@pytest.mark.slow  # 19 s; bad cubes' errors are in tests/test_io.py (2 idle cores, 2026-12-02): pytest -m slow
def test_external_dataset_with_a_bad_cube_fails_naming_it(workdir, out, tmp_path):
    """A dataset outside the working directory, in the raw format, whose dark cube has the wrong shape."""
    data = tmp_path / "bench"
    shutil.copytree(out / "raw", data)
    document = yaml.safe_load((data / "dataset.yaml").read_text())
    document["name"] = "bench-broken"
    (data / "dataset.yaml").write_text(yaml.safe_dump(document))
    dark = data / document["dark"]["files"][0]
    write_cube(dark, [np.zeros((3, 40, 45))], shape=(40, 45), n_frames=3)
    result = snakemake(workdir, "--config", f"dataset={data / 'dataset.yaml'}", check=False)
    assert result.returncode != 0
    log = (workdir / "results" / "bench-broken" / "logs" / "measure_dark.log").read_text()
    assert str(dark) in log and "frames are 40x45" in log and "Traceback" in log
    said = result.stdout + result.stderr  # the terminal: the problem in one line, once, no traceback
    lines = [line for line in said.splitlines() if "frames are 40x45" in line]
    assert lines == [f"dice: measure_dark failed: {dark}: frames are 40x45 (rows x cols) but the detector is "
                     f"{lines[0].split('detector is ')[1].split()[0]} (traceback in "
                     "results/bench-broken/logs/measure_dark.log)"]
    assert "Traceback" not in said
    assert not (workdir / "results" / "bench-broken" / "calibration" / "dark.nc").exists()
    assert not list((workdir / "results" / "bench-broken").rglob("*.part"))


@pytest.mark.slow  # 53 s: three dry runs of other datasets (2 idle cores, 2026-12-02): pytest -m slow
def test_modes_without_their_calibration_are_skipped_or_refused(workdir, out, tmp_path):
    """A dataset without flats: the flat modes are skipped, saying why (the dataset format lets any
    section be absent); a metrology pair that the dataset does not have: a clear error."""
    document = yaml.safe_load((out / "raw" / "dataset.yaml").read_text())
    del document["flats"]
    document["name"] = "bench-no-flats"
    for section in ("dark", "stars", "metrology"):  # the raw files stay where they are
        document.setdefault(section, {})
    manifest = tmp_path / "dataset.yaml"
    raw = out / "raw"
    document["dark"]["files"] = [str(raw / f) for f in document["dark"]["files"]]
    for position in document["stars"]["positions"]:
        position["files"] = [str(raw / f) for f in position["files"]]
    for baseline in document["metrology"]["baselines"].values():
        baseline["files"] = [str(raw / f) for f in baseline["files"]]
    manifest.write_text(yaml.safe_dump(document))
    result = snakemake(workdir, "-n", "--config", f"dataset={manifest}")
    said = result.stdout + result.stderr
    assert said.count("skipping centroid mode flat: the dataset has no flat field") == 1
    assert "skipping centroid mode flat+metrology: the dataset has no flat field" in said
    assert "centroids/raw.nc" in said and "centroids/metrology.nc" in said and "centroids/flat.nc" not in said
    # a reduction sweep's points evaluate the workflow again, as modules: the reason is still said once
    (workdir / "half.yaml").write_text(yaml.safe_dump({"sweeps": {"half": {
        "study": "reduction", "parameter": "centroids.half_size", "values": [3, 4]}}}))
    result = snakemake(workdir, "-n", "--config", f"dataset={manifest}", "--configfile", "half.yaml")
    said = result.stdout + result.stderr
    assert said.count("skipping centroid mode flat: the dataset has no flat field") == 1
    (workdir / "bad_pair.yaml").write_text("centroids:\n  pair: P99\n")
    result = snakemake(workdir, "-n", "--config", "dataset=ci", "--configfile", "bad_pair.yaml", check=False)
    assert result.returncode != 0
    assert "centroids.pair 'P99' is not a pair of" in result.stdout + result.stderr


@pytest.mark.slow  # 13 s dry run (2 idle cores, 2026-12-02): pytest -m slow
def test_a_bench_geometry_plans_the_metrology_and_every_mode(workdir, out, tmp_path):
    """A format-1.1 manifest (metrology.geometry) plans the whole metrology and every centroid mode; the
    spherical-wave reduction itself runs in the default preset's job (slow test) and tests/test_geometry.py."""
    document = yaml.safe_load((out / "raw" / "dataset.yaml").read_text())
    document["name"] = "bench-spherical"
    raw = out / "raw"
    for entry in [document["dark"], *document["flats"].values(), *document["metrology"]["baselines"].values(),
                  *document["stars"]["positions"]]:
        entry["files"] = [str(raw / f) for f in entry["files"]]
    document["metrology"]["geometry"] = {
        "wavelength": 633.0e-9, "pixel_pitch": 24.0e-6,
        "fibers": {"F1": [0.0153, 0.0201, 0.6], "F2": [0.0120, 0.0260, 0.6], "F4": [0.0087, 0.0201, 0.6]},
        "baseline_fibers": {b: ["F1", "F4"] if b.startswith("H") else ["F2", "F4"]
                            for b in document["metrology"]["baselines"]}}
    manifest = tmp_path / "dataset.yaml"
    manifest.write_text(yaml.safe_dump(document))
    result = snakemake(workdir, "-n", "--config", f"dataset={manifest}")
    said = result.stdout + result.stderr
    # every mode: the chromatic one, which a single wavelength cannot have, left out unsaid
    assert "skipping" not in said
    for planned in ("rule fit_fringes", "rule allan_deviation", "rule deproject_offsets", "metrology/H1H4.nc",
                    "calibration/offsets_", "centroids/metrology.nc", "centroids/flat+metrology.nc"):
        assert planned in said, planned


def test_a_dataset_of_several_wavelengths_plans_its_calibration_across_wavelength_and_the_chromatic_mode(workdir):
    """The chromatic preset (format 1.2: lasers at 633, 450 and 800 nm, a laser flat at each, broadband stars): every
    wavelength's pairs reduced as a single wavelength's, calibration/chromatic.nc from them, the chromatic mode and
    its figure; nothing skipped. (The reduction itself is the slow test below.)"""
    result = snakemake(workdir, "-n", "--config", "dataset=chromatic")
    said = result.stdout + result.stderr
    assert "skipping" not in said
    for planned in ("rule chromatic_calibration", "calibration/chromatic.nc", "figures/chromatic.png",
                    "metrology/H1H4_450.nc", "calibration/offsets_P14_800.nc", "calibration/flats/prnu_laser_450.nc",
                    "centroids/flat+metrology+chromatic.nc", "centroids/gaussian/flat+metrology+chromatic.nc"):
        assert planned in said, planned


@pytest.mark.slow  # 4 min 45 s on 2 shared cores (load 5; 2026-12-05): 109 jobs, then 8 dry runs
def test_a_dataset_of_several_wavelengths_is_reduced_wavelength_by_wavelength_and_across(tmp_path):
    """The chromatic preset through the workflow: each wavelength's offsets against the truth at that wavelength
    within 1.2 of their photon floor (measured 1.0), calibration/chromatic.nc holding each wavelength's
    calibration, and the chromatic mode's rows in the accuracy table."""
    root = copy_repository(tmp_path)
    snakemake(root, "--config", "dataset=chromatic", timeout=1800)
    out = root / "results" / "sim-chromatic"
    truth = read_product(out / "raw" / "truth.nc")
    product = read_product(out / "calibration" / "chromatic.nc")
    assert list(product["pair"].values) == ["P14", "P14_450", "P14_800"]
    np.testing.assert_allclose(product["wavelength"].values, [633e-9, 450e-9, 800e-9])
    assert product.attrs["reference_wavelength"] == 633e-9 and "absorption length" in product.attrs["model"]
    for pair, wavelength in zip(product["pair"].values, product["wavelength"].values):
        offsets = read_product(out / "calibration" / f"offsets_{pair}.nc")
        at = truth.sel(wavelength=wavelength)
        ratios = pair_errors_over_floors(offsets, {"dx": at["dx_wavelength"], "dy": at["dy_wavelength"]})
        assert max(ratios) < 1.2, (pair, ratios)
        np.testing.assert_array_equal(product["dx"].sel(wavelength=wavelength).values, offsets["dx"].values)
        flat = read_product(out / "calibration" / "flats" / f"prnu_laser_{round(wavelength * 1e9)}.nc")
        np.testing.assert_array_equal(product["sensitivity"].sel(wavelength=wavelength).values, flat["prnu"].values)
    rows = read_accuracy_table(out / "tables" / "accuracy.csv")
    assert {r["grouping"] for r in rows if r["mode"] == "flat+metrology+chromatic"} == {"position", "group"}
    assert "Metrology + chromatic" in (out / "tables" / "accuracy.tex").read_text()
    # the settings of the steps that only a dataset of several wavelengths has re-run them, and only them
    for key in ("prf.order", "centroids.spectrum"):
        check_key_triggers_its_steps(root, key, tmp_path, dataset="chromatic")


@pytest.mark.slow
def test_default_preset_against_truth(tmp_path):
    """The README's main job (about 30 s): dark noise and PRNU of the 80x84 testbed against truth."""
    root = copy_repository(tmp_path)
    snakemake(root)
    out = root / "results" / "sim-default"
    manifest = load_manifest(out / "raw" / "dataset.yaml")
    truth = read_product(out / "raw" / "truth.nc")
    sl = manifest.detector.science_slices
    dark = read_product(out / "calibration/dark.nc")
    ratio = dark["noise"].values[sl] / truth["read_noise"].values[sl]
    assert np.mean(ratio) == pytest.approx(1.0, abs=0.01)  # 400 frames: 3.5% per pixel, 0.04% on the mean
    prnu = read_product(out / "calibration/prnu.nc")
    expected, _ = remove_gradient(truth["sensitivity"].values, manifest.detector.science_mask())
    error = prnu["prnu"].values[sl] - expected[sl] / expected[sl].mean()
    assert np.sqrt(np.mean(error**2)) < 1.5 * float(prnu["photon_noise_limit_rms"])
    diff = read_product(out / "calibration/prnu_difference_fiber_b.nc")
    assert float(diff["difference_rms"]) < 1.5 * float(diff["photon_noise_limit_rms"])
    # metrology on the default preset (PRNU 2e-3 left in the fringe data, spherical waves of the paper's
    # bench, nominal tips 0.5-1 mm off): along each pixel's local wavevector, once the affine part and
    # the declared unobservable modes are removed from the truth too, within 1.2x the floor
    for baseline in manifest.baselines:
        metrology = read_product(out / "metrology" / f"{baseline}.nc")
        good = np.isfinite(metrology["projected_offset"].values)
        rows, cols = np.nonzero(good)
        k = np.stack([metrology["kx_local"].values[good], metrology["ky_local"].values[good]])
        n = k / np.hypot(*k)
        projected = n[0] * truth["dx"].values[good] + n[1] * truth["dy"].values[good]
        basis = [np.ones(rows.size), cols, rows, *metrology["unobservable_offset"].values[:, good]]
        q, _ = np.linalg.qr(np.array(basis, float).T)
        error = metrology["projected_offset"].values[good] - (projected - q @ (q.T @ projected))
        assert np.sqrt(np.mean(error**2)) < 1.2 * float(metrology["photon_noise_floor_rms"]), baseline
        assert metrology.sizes["mode"] >= 1 and "gauge_difference_floor" in metrology, baseline
        # a bench without stray light: its diagnosis finds none (false-alarm rate 1e-3 a baseline)
        assert int(read_product(out / "calibration" / f"stray_light_{baseline}.nc")["n_components"]) == 0, baseline
        # Allan deviations of the same baseline: white, and at the photon limit to the last point
        ds = read_product(out / "allan" / f"{baseline}.nc")
        assert float(ds["slope_batch_means"]) == pytest.approx(-0.5, abs=0.05), baseline
        last = ds.isel(n_frames=-1)
        assert float(last["deviation_mean"]) == pytest.approx(float(last["photon_limit_pixel"]), rel=0.2)
        # the largest group, fitted as a whole, at the global solution's floor scaled to its frames
        scaled = float(metrology["photon_noise_floor_rms"]) * np.sqrt(metrology.sizes["frame"] / float(last["n_frames"]))
        assert float(last["deviation_mean"]) == pytest.approx(scaled, rel=0.1), baseline
    # each pair's dx, dy within 1.2x their floors once the affine part and the declared modes are removed
    for pair in manifest.pairs:
        offsets = read_product(out / "calibration" / f"offsets_{pair}.nc")
        assert max(pair_errors_over_floors(offsets, truth)) < 1.2, pair
    # the accuracy table: all four modes in both groupings, flat + metrology best, each calibration
    # helping, and each accuracy (p) consistent with the same Procrustes accuracy of its true errors
    from dice_core import accuracies

    table = read_accuracy_table(out / "tables" / "accuracy.csv")
    assert len(table) == 20  # two methods, five modes, two groupings
    rows = {(r["mode"], r["grouping"]): r for r in table if r["method"] == "fourier"}
    assert len(rows) == 10
    value = {key: float(r["accuracy"]) for key, r in rows.items()}
    for grouping in ("position", "group"):
        assert value["flat+metrology", grouping] == min(value[m, grouping] for m in
                                                         ("raw", "flat", "metrology", "flat+metrology"))
    assert value["flat", "position"] < value["raw", "position"]
    assert value["flat+metrology", "position"] < value["flat", "position"]
    # The true positions alone leave a residual no superimposition removes (the preset's tip-tilt
    # changes the plate scale unevenly, appendix D): 3.2e-4 pixel after the correction factors. It does
    # not depend on the centroid errors, so the two residuals' variances add, to first order (the
    # superimposition is linear in errors of 1e-4 pixel). The correction factors are for white errors;
    # applied to this smooth residual they give a number of its size, which is all the check needs.
    true_xy = np.stack([truth["star_x"].values, truth["star_y"].values], axis=-1)
    geometry = accuracies.accuracy(true_xy, trials=500).accuracy
    layout = true_xy[0]
    for mode in ("raw", "flat", "metrology", "flat+metrology"):
        ds = read_product(out / "centroids" / f"{mode}.nc")
        errors = np.stack([ds["x"].values - truth["star_x"].values, ds["y"].values - truth["star_y"].values], -1)
        truth_based = np.hypot(accuracies.accuracy(layout + errors, trials=500).accuracy, geometry)
        row = rows[mode, "position"]
        assert abs(float(row["accuracy"]) - truth_based) < 3 * float(row["error"]), mode


# Bright stars on the ci preset (docs/centroids.md, "In the accuracy table"): 1600 frames a position take the
# Cramer-Rao bound to 2.2e-5 pixel, below the 3.5e-5 of the widths' error that the superimposition sees (the
# part that changes from position to position); 12 positions give Procrustes 54 degrees of freedom over
# positions, 6 groups 24 over groups; 2000 metrology and 400 flat frames take the calibrations' own noise
# below the widths' error; no tip-tilt, whose off-axis shear Procrustes cannot take out (docs/astrometry.md)
# and which would swamp the difference.
BRIGHT_CI = {
    "simulation": {"stars.frames": 1600, "stars.positions": 12, "stars.tip_tilt_pv": 0.0, "metrology.frames": 2000,
                   "flats.frames": 400},
    "centroids": {"modes": ["flat+metrology", "flat+metrology+width"], "methods": ["fourier"]},
    "astrometry": {"groups": 6},
}


@pytest.mark.slow  # a whole ci reduction with 4x the calibration frames and 12 positions of 1600 frames
def test_with_bright_stars_the_width_mode_beats_flat_and_metrology_in_the_accuracy_table(tmp_path):
    """The workflow's own calibrations (flat, offsets and PRF width maps measured from the simulated frames)
    and its accuracy table: flat+metrology+width below flat+metrology in both groupings. Expected: the
    squared accuracies differ by the 3.5e-5 pixel of the widths' error squared, which the noise common to
    both modes (about 2.9e-5) moves by about a quarter of itself, 4 sigma; measured 0.65 (p) and 0.56 (g)
    of flat+metrology at the preset's seed, 0.87 and 0.85 at seed 8 (docs/centroids.md). 7.5 min measured
    on 2 shared cores."""
    from dice_core import simulation

    root = copy_repository(tmp_path)
    (root / "bright.yaml").write_text(yaml.safe_dump(BRIGHT_CI))
    name = simulation.load_preset(root / "config" / "presets" / "ci.yaml", overrides=BRIGHT_CI["simulation"]).name
    table = root / "results" / name / "tables" / "accuracy.csv"
    snakemake(root, "--config", "dataset=ci", "--configfile=bright.yaml", str(table.relative_to(root)), timeout=3600)
    value = {(r["mode"], r["grouping"]): float(r["accuracy"]) for r in read_accuracy_table(table)
             if r["superimposition"] == "procrustes"}
    for grouping in ("position", "group"):
        assert value["flat+metrology+width", grouping] < value["flat+metrology", grouping], (grouping, value)


# 79 s; the spherical fit at its floor is in tests/test_geometry.py
@pytest.mark.slow  # (2 idle cores, 2026-12-02): pytest -m slow
def test_spherical_wave_fringes_are_reduced_at_the_floor_through_the_workflow(workdir):
    """The ci preset with the paper's bench (fibers 600 mm away, midpoints 9-18 mm off the normal, nominal
    tips 0.5-1 mm off): metrology, deprojection and Allan run, the offsets product declares its unobservable
    modes, and dx, dy are at their photon floor once those and the affine part are removed from the truth."""
    preset = yaml.safe_load((workdir / "config" / "presets" / "ci.yaml").read_text())
    preset["name"] = "sim-ci-spherical"
    preset["metrology"].update(spherical=True, baselines={
        "H1H4": {"period": 2.4, "angle_deg": 2.0, "midpoint": [0.012, 0.006]},
        "V1V4": {"period": 2.4, "angle_deg": 93.0, "midpoint": [-0.004, 0.008]},
        "H2H4": {"period": 4.0, "angle_deg": -3.0, "midpoint": [0.016, -0.009]},
        "V2V4": {"period": 4.0, "angle_deg": 88.5, "midpoint": [-0.011, -0.010]}})
    (workdir / "config" / "presets" / "ci-spherical.yaml").write_text(yaml.safe_dump(preset))
    out = workdir / "results" / "sim-ci-spherical"
    snakemake(workdir, "results/sim-ci-spherical/calibration/offsets_P14.nc", "results/sim-ci-spherical/allan/H1H4.nc",
              "--config", "dataset=ci-spherical")
    metrology = read_product(out / "metrology" / "H1H4.nc")
    assert metrology["fiber_position"].dims == ("fiber", "xyz") and metrology.sizes["mode"] >= 1
    assert "tips of fibers H1H4a and H1H4b refined in" in (out / "logs" / "fit_fringes_H1H4.log").read_text()
    # what a plane-wave fit would have left, against the true tips' surface minus its best plane
    truth = read_product(out / "raw" / "truth.nc")
    good = np.isfinite(metrology["plane_wave_departure"].values)
    rows, cols = np.nonzero(good)
    tips = dict(zip(truth["fiber"].values, truth["fiber_position"].values))
    bench = load_manifest(out / "raw" / "dataset.yaml").geometry
    phase, gx, gy = two_source_phase(cols, rows, tips["H1H4a"], tips["H1H4b"], wavelength=bench.wavelength,
                                     pixel_pitch=bench.pixel_pitch)
    design = np.column_stack([np.ones(rows.size), cols, rows])
    expected = (phase - design @ np.linalg.lstsq(design, phase, rcond=None)[0]) / np.hypot(gx, gy)
    departure = metrology["plane_wave_departure"].values[good]
    assert min(np.std(departure - expected), np.std(departure + expected)) < 0.3 * np.std(expected)
    offsets = read_product(out / "calibration" / "offsets_P14.nc")
    assert offsets.sizes["mode"] >= 2
    assert max(pair_errors_over_floors(offsets, truth)) < 1.2
    allan = read_product(out / "allan" / "H1H4.nc")
    assert float(allan["deviation_mean"][0]) < 1.5 * float(allan["photon_limit_pixel"][0])
    # a manifest whose nominal tips are not the bench's (H1H4's 20 mm apart in z, a defocus the fringes
    # deny): the fit stops with an error naming the manifest and its geometry, and writes nothing
    document = yaml.safe_load((out / "raw" / "dataset.yaml").read_text())
    document["name"] = "bench-wrong-tips"
    document["dark"]["files"] = [str(out / "raw" / f) for f in document["dark"]["files"]]
    for group in ("flats", "metrology"):
        for entry in document[group].values() if group == "flats" else document[group]["baselines"].values():
            entry["files"] = [str(out / "raw" / f) for f in entry["files"]]
    for position in document["stars"]["positions"]:
        position["files"] = [str(out / "raw" / f) for f in position["files"]]
    fibers = document["metrology"]["geometry"]["fibers"]
    fibers["H1H4a"][2] += 0.01
    fibers["H1H4b"][2] -= 0.01
    manifest = workdir / "wrong-tips.yaml"
    manifest.write_text(yaml.safe_dump(document))
    result = snakemake(workdir, "results/bench-wrong-tips/metrology/H1H4.nc", "--config", f"dataset={manifest}",
                       check=False)
    assert result.returncode != 0
    log = (workdir / "results" / "bench-wrong-tips" / "logs" / "fit_fringes_H1H4.log").read_text()
    assert f"{manifest}: metrology.geometry: baseline H1H4: the pixel phases move the tip of fiber H1H4" in log
    assert not (workdir / "results" / "bench-wrong-tips" / "metrology" / "H1H4.nc").exists()


@pytest.mark.slow  # 53 s: study points run, then planned (2 idle cores, 2026-12-02): pytest -m slow
def test_a_sweep_point_added_runs_only_its_job_and_one_removed_touches_no_other(workdir):
    """Sweeps are Paramspace points: each its own job and folder, the summary gathering whichever are listed."""
    target = "results/sweeps/tiny/summary.csv"

    def sweep(values):
        (workdir / "sweep.yaml").write_text(yaml.safe_dump({"sweeps": {"tiny": {
            "study": "error_propagation", "parameter": "source", "values": values,
            "options": {"trials": 20, "amplitudes": [1e-3]}}}}))
        run = snakemake(workdir, target, "--config", "dataset=ci", "--configfile=sweep.yaml")
        return run.stdout + run.stderr

    points = workdir / "results" / "sweeps" / "tiny"
    ran = sweep(["prnu", "read"])
    assert ran.count("rule sweep_point:") == 2
    before = {p: p.stat().st_mtime_ns for p in points.glob("*/point.nc")}
    assert sorted(p.parent.name for p in before) == ["source~prnu", "source~read"]
    ran = sweep(["prnu", "read", "offsets"])
    assert ran.count("rule sweep_point:") == 1 and "point=source~offsets" in ran and "rule sweep_summary:" in ran
    assert all(p.stat().st_mtime_ns == mtime for p, mtime in before.items())
    ran = sweep(["prnu", "offsets"])
    assert "rule sweep_point:" not in ran and "rule sweep_summary:" in ran
    assert all(p.stat().st_mtime_ns == mtime for p, mtime in before.items())  # read's product kept, untouched
    summary = (workdir / target).read_text().splitlines()
    assert summary[0].startswith("source,") and [line.split(",")[0] for line in summary[1:]] == ["prnu", "offsets"]
    (workdir / "sweep.yaml").write_text(yaml.safe_dump({"sweeps": {"tiny": {
        "study": "error_propagation", "points": [{"source": "prnu"}, {"source": "read", "trials": 30}]}}}))
    bad = snakemake(workdir, target, "-n", "--config", "dataset=ci", "--configfile=sweep.yaml", check=False)
    assert bad.returncode != 0 and "every point must set the same parameters" in bad.stdout + bad.stderr


@pytest.mark.slow  # 12 s dry run (2 idle cores, 2026-12-02): pytest -m slow
def test_the_paper_target_plans_the_studies_and_the_comparison(workdir):
    # every point forced: an earlier test's paper run (paper_run, other sweeps) may have made some of them
    plan = snakemake(workdir, "paper", "-n", "--forcerun", "sweep_point", "--config", "dataset=ci").stdout
    for rule in ("sweep_point", "sweep_summary", "plot_offset_bias", "error_propagation_table", "paper_comparison",
                 "plot_chromatic_study"):
        assert f"rule {rule}:" in plan
    # a job a point of each sweep config paper names (its studies), as config sweeps plans them: today 2 PRNU
    # levels, 4 sources x 2 weightings, 12 stray-light points, 2 chromatic amplitudes x 3 spectra (28)
    from dice_core.planning import plan_sweep

    config = yaml.safe_load((workdir / "config" / "config.yaml").read_text())
    points = sum(len(plan_sweep(name, config["sweeps"][name]).folders) for name in config["paper"].values())
    assert points >= 4 and plan.count("rule sweep_point:") == points
    assert "rule fit_fringes:" not in plan  # the ci reduction is done: the paper target adds only its own jobs


@pytest.mark.slow  # a whole workflow run or more (4 min on 2 shared cores): pytest -m slow
def test_a_reduction_sweep_reruns_the_workflow_per_point_in_its_own_folder(workdir, out):
    """Study reduction: each point is the whole workflow again (a Snakemake module) with the point's config,
    reading the run's raw files; a point added runs only its own jobs; the run's own products are untouched."""
    target = "results/sweeps/half/summary.csv"

    def sweep(values, *extra):
        (workdir / "reduction.yaml").write_text(yaml.safe_dump({"sweeps": {"half": {
            "study": "reduction", "parameter": "centroids.half_size", "values": values}}}))
        run = snakemake(workdir, target, *extra, "--config", "dataset=ci", "--configfile=reduction.yaml")
        return run.stdout + run.stderr

    main_products = {p: p.stat().st_mtime_ns for p in out.rglob("*.nc")}
    ran = sweep([3, 4])  # windows of 7x7 and 9x9 pixels (the ci preset's stars allow 9x9 at most)
    assert "rule simulate_" not in ran and "rule sweep_half_half_size_3_" in ran and "_measure_centroids:" in ran
    summary = (workdir / target).read_text().splitlines()
    assert summary[0].startswith("centroids.half_size,") and {line.split(",")[0] for line in summary[1:]} == {"3", "4"}
    assert "accuracy [pixel]" in summary[0].split(",")
    points = workdir / "results" / "sweeps" / "half"
    tables = [(points / f"half_size~{h}" / "sim-ci" / "tables" / "accuracy.csv").read_text() for h in (3, 4)]
    assert all(t.startswith("flat,metrology,grouping,accuracy,error") for t in tables)
    assert tables[0] != tables[1]  # the parameter reached the centroids
    assert read_product(points / "half_size~3" / "sim-ci" / "centroids" / "raw.nc").attrs["configuration"].count(
        '"half_size": 3') == 1
    before = {p: p.stat().st_mtime_ns for p in (workdir / "results" / "sweeps" / "half").rglob("*.nc")}
    plan = sweep([3, 4, 2], "-n")
    planned = {line.split()[1].rstrip(":") for line in plan.splitlines() if line.startswith(("rule ", "localrule "))}
    assert planned and all(r.startswith("sweep_half_half_size_2_") for r in planned - {"reduction_sweep_summary"})
    # the first point removed: the other's modules keep their names, so nothing of theirs is planned
    plan = sweep([4], "-n")
    planned = {line.split()[1].rstrip(":") for line in plan.splitlines() if line.startswith(("rule ", "localrule "))}
    assert planned == {"reduction_sweep_summary"}
    assert all(p.stat().st_mtime_ns == t for p, t in before.items())
    assert all(p.stat().st_mtime_ns == t for p, t in main_products.items())
    # a simulation key makes the point simulate its own dataset, in its own folder, named by its overrides
    (workdir / "reduction.yaml").write_text(yaml.safe_dump({"sweeps": {"wide": {
        "study": "reduction", "parameter": "simulation.detector.prf_width_spread", "values": [0.03]}}}))
    plan = snakemake(workdir, "results/sweeps/wide/summary.csv", "-n", "--config", "dataset=ci",
                     "--configfile=reduction.yaml").stdout
    assert "simulate_truth:" in plan and "results/sweeps/wide/prf_width_spread~0.03/sim-ci-" in plan
    assert "rule sweep_wide_prf_width_spread_0_03_" in plan


def planned_rules(plan):
    return {line.split()[1].rstrip(":") for line in plan.splitlines() if line.startswith(("rule ", "localrule "))}


@pytest.mark.slow  # 25 s of dry runs (2 idle cores, 2026-12-02): pytest -m slow
def test_a_reduction_sweep_over_lists_of_modes_gives_each_point_its_folder(workdir, out):
    """A list value (centroids.modes) is one point: its folder named by the joined values; the run's own accuracy
    table is not the sweep's."""
    (workdir / "modes.yaml").write_text(yaml.safe_dump({"sweeps": {"modes": {
        "study": "reduction", "parameter": "centroids.modes", "values": [["raw"], ["raw", "flat+metrology"]]}}}))
    plan = snakemake(workdir, "results/sweeps/modes/summary.csv", "-n", "--config", "dataset=ci",
                     "--configfile=modes.yaml").stdout
    for folder in ("modes~raw", "modes~raw,flat+metrology"):
        assert f"results/sweeps/modes/{folder}/sim-ci/tables/accuracy.csv" in plan
    assert "results/sweeps/modes/modes~raw/sim-ci/centroids/flat+metrology.nc" not in plan
    assert "results/sim-ci/tables/accuracy.csv" not in plan and "rule simulate_" not in plan


@pytest.mark.slow  # 24 s of dry runs (2 idle cores, 2026-12-02): pytest -m slow
def test_the_centroid_method_of_the_products_does_not_follow_the_list_order(workdir):
    """centroids/<mode>.nc holds centroids.method's centroids, whatever the order of centroids.methods."""
    (workdir / "order.yaml").write_text("centroids:\n  methods: [gaussian, fourier]\n")
    plan = snakemake(workdir, "-n", "--config", "dataset=ci", "--configfile", "order.yaml").stdout
    assert "Nothing to be done" in plan, plan
    (workdir / "method.yaml").write_text("centroids:\n  method: gaussian\n")
    plan = snakemake(workdir, "-n", "--config", "dataset=ci", "--configfile", "method.yaml").stdout
    assert "results/sim-ci/centroids/fourier/raw.nc" in plan and "rule measure_centroids_by_method:" in plan


@pytest.mark.slow  # 12 s dry run (2 idle cores, 2026-12-02): pytest -m slow
def test_simulation_overrides_are_another_dataset_with_its_own_results(workdir):
    """A top-level simulation: key changes the simulated data, so it changes the results' name too: the preset's
    own products are never overwritten by another dataset's."""
    (workdir / "overrides.yaml").write_text(yaml.safe_dump({"simulation": {"detector.prnu_rms": "3e-3"}}))
    plan = snakemake(workdir, "-n", "--config", "dataset=ci", "--configfile", "overrides.yaml").stdout
    assert "results/sim-ci-" in plan and "results/sim-ci/" not in plan
    assert "rule simulate_truth:" in plan


# The paper target on the ci preset, its studies shrunk (sweeps of their own names, so as to leave the
# configured ones alone): about a minute beyond the ci workflow that the module's fixture runs.
PAPER_CI = {
    "sweeps": {
        "bias_ci": {"study": "offset_bias", "parameter": "detector.prnu_rms", "values": [5.0e-5, 2.0e-3],
                    "bench": {"metrology.frames": 2000}, "options": {"noiseless_frames": 1000, "noiseless_draws": 2}},
        "errors_ci": {"study": "error_propagation", "grid": {"source": ["prnu", "photon", "offsets", "read"],
                                                             "weighting": ["pipeline", "uniform"]},
                      "options": {"trials": 20, "amplitudes": [1.0e-3]}},
        # the stray-light study at 300 frames: the field ratio 1e-3 point (its rows) and one at 3e-3
        "stray_ci": {"study": "stray_light", "parameter": "stray_light.field_ratio", "values": [1.0e-3, 3.0e-3],
                     "bench": {"metrology.frames": 300}},
    },
    "paper": {"offset_bias": "bias_ci", "error_propagation": "errors_ci", "stray_light": "stray_ci"},
}


@pytest.fixture(scope="module")
def paper_run(workdir):
    (workdir / "paper_ci.yaml").write_text(yaml.safe_dump(PAPER_CI))
    run = snakemake(workdir, "paper", "--config", "dataset=ci", "--configfile=paper_ci.yaml")
    return run.stdout + run.stderr


@pytest.mark.slow  # the paper target on ci: 63 s beyond the ci run (2 idle cores, 2026-12-02): pytest -m slow
def test_the_paper_target_runs_and_its_tables_follow_the_contract(paper_run, out):
    assert "rule paper_comparison:" in paper_run and "rule fit_fringes:" not in paper_run
    with open(out / "tables" / "paper_comparison.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert list(rows[0])[:6] == ["quantity", "section", "paper", "ours", "error", "unit"]
    quantities = [r["quantity"] for r in rows]
    assert len(set(quantities)) == len(quantities)  # one row per number
    by_quantity = {r["quantity"]: r for r in rows}
    for quantity in ("centroid error per unit PRNU RSD", "centroid error per unit PRNU RSD (unweighted fit)",
                     "Procrustes deflation factor, 5 stars, 33 positions", "accuracy, flat and metrology (p)",
                     "offset bias rms of the paper's method, PRNU RSD 2e-3",
                     "offset error rms of ours (true flat), with photon noise, PRNU RSD 2e-3",
                     "offset bias rms of the paper's method, noiseless, rms over the PRNU patterns, PRNU RSD 5e-5"):
        assert quantity in by_quantity and float(by_quantity[quantity]["ours"]) > 0
    assert by_quantity["offset error rms of ours (true flat), with photon noise, PRNU RSD 2e-3"]["paper"] == ""
    allan = [q for q in quantities if q.startswith("Allan deviation of the largest group, individual pixels (")]
    assert len(allan) == 4 and all("frames per group" in q for q in allan)  # each ci baseline, as measured
    assert float(by_quantity["Procrustes deflation factor, 5 stars, 33 positions"]["ours"]) == pytest.approx(1.4,
                                                                                                          abs=0.06)
    with open(out / "tables" / "error_propagation.csv", newline="") as handle:
        errors = list(csv.DictReader(handle))
    assert list(errors[0])[:5] == ["source", "normalisation", "coefficient", "error", "paper_coefficient"]
    assert [r["source"] for r in errors] == ["prnu", "photon", "offsets", "read"]
    assert (out / "figures" / "error_propagation.png").is_file() and (out / "figures" / "offset_bias.png").is_file()
    assert (out / "figures" / "stray_light_study.png").is_file()
    stray = [q for q in quantities if q.startswith("pixel-offset accuracy, stray light its main noise")]
    assert any("field ratio 1e-3, stray light left in, study" in q for q in stray), stray
    assert (out / "report" / "paper_reproduction.pdf").read_bytes()[:5] == b"%PDF-"


@pytest.mark.slow  # 39 s beyond the paper target's run (2 idle cores, 2026-12-02): pytest -m slow
def test_a_plot_edit_reruns_the_papers_plots_and_no_monte_carlo(paper_run, workdir):
    rules = rules_planned_after_editing(workdir, "plotting", "paper", "--config", "dataset=ci",
                                        "--configfile=paper_ci.yaml")
    assert {"plot_error_propagation", "plot_offset_bias", "paper_comparison", "paper_pdf"} <= rules
    assert not rules & {"error_propagation_table", "procrustes_deflation", "sweep_point", "accuracy_table"}


def test_a_fit_split_across_jobs_writes_the_single_jobs_product_bit_for_bit(workdir, out):
    """metrology.split on the ci preset: one baseline's fit as jobs (the state before pass 1, per pass a job
    per part of the files and one that sums them, the product), from the raw files and calibration of the ci
    run. The product is the single job's, every variable bit for bit, and records the same inputs with the
    same checksums (the cubes' from pass 1's parts: no later job reads the cubes to hash them). Four passes
    at most instead of ten, to keep the test short: the fit converges before (checked), so the single job
    with either stops at the same pass. Each job asks for what its benchmark measured."""
    import json

    (workdir / "split.yaml").write_text("metrology:\n  split: true\n  max_passes: 4\n")
    # the ci run's calibration products, bytes and times kept: up to date, not made again
    shutil.copytree(out / "calibration", workdir / "split-results" / "sim-ci" / "calibration")
    target = "split-results/sim-ci/metrology/H1H4.nc"
    run = snakemake(workdir, target, "--config", f"dataset={out / 'raw' / 'dataset.yaml'}",
                    "results=split-results", "--configfile", "split.yaml")
    said = run.stdout + run.stderr
    counts = dict(re.findall(r"^(\w+)\s+(\d+)$", said, re.M))
    assert counts == {"fit_start": "1", "fit_part": "8", "fit_reduce": "4", "fit_finish": "1", "total": "14"}
    single, split = read_product(out / "metrology/H1H4.nc"), read_product(workdir / target)
    assert set(single.data_vars) == set(split.data_vars)
    for name in single.data_vars:
        assert single[name].identical(split[name]), name
    assert json.loads(split.attrs["inputs"]) == json.loads(single.attrs["inputs"])
    logs = workdir / "split-results" / "sim-ci" / "logs"
    n_pass = int(single["iteration"].values[-1])
    assert 2 <= n_pass < 4
    converged = f"converged to 1.0e-07 pixel at pass {n_pass}"
    assert converged in (out / "logs" / "fit_fringes_H1H4.log").read_text()
    assert converged in (logs / "fit_finish_H1H4.log").read_text()
    assert "state carried over" in (logs / f"fit_reduce_H1H4_{n_pass + 1}.log").read_text()
    assert "nothing to read" in (logs / f"fit_part_H1H4_{n_pass + 1}_0.log").read_text()
    part = (logs / "fit_part_H1H4_1_1.log").read_text()
    assert "pass 1, part 2 of 2: 150 frames of 1 file(s)" in part and "BLAS threads: 1" in part
    # pass 1 hashed the part's file as it read it; the later passes take its digest from the results' store
    assert "the SHA-256 of 0 of the part's 1 file(s) taken" in part
    assert "the SHA-256 of 1 of the part's 1 file(s) taken" in (logs / "fit_part_H1H4_2_1.log").read_text()
    jobs = planned_jobs(said, r"fit_\w+")
    assert len(jobs) == 14
    for rule, block in jobs:
        asked = dict(re.findall(r"\b(mem_mb|runtime)=(\d+)", block))
        within_what_it_asked(workdir, rule, block, asked)
        if rule == "fit_part":  # a part declares its own file (ci: one of 150 frames a part), no other
            part = int(re.search(r"part_(\d+)\.nc", block).group(1))
            assert re.findall(r"H1H4_\d+\.fits", block) == [f"H1H4_{part:03d}.fits"], block
    # the states and parts are temporary: removed once the product is written, which is up to date without
    # them; a changed cube (here its time, put back after) reruns every pass from the start. Snakemake compares
    # the contents of inputs under --max-checksum-file-size (1 MB) instead of their times: ci's cubes are that
    # small, a bench's are not (0: by time, as for a bench's)
    assert not list((workdir / "split-results" / "sim-ci" / "metrology" / "split").rglob("*.nc"))
    again = (target, "--config", f"dataset={out / 'raw' / 'dataset.yaml'}", "results=split-results",
             "--configfile", "split.yaml")
    assert "Nothing to be done" in snakemake(workdir, "-n", *again).stdout
    cube = out / "raw" / "metrology" / "H1H4_001.fits"
    stat = cube.stat()
    try:
        os.utime(cube, ns=(stat.st_atime_ns, time.time_ns()))  # newer than the product
        plan = snakemake(workdir, "-n", "--max-checksum-file-size", "0", *again).stdout
    finally:
        os.utime(cube, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert dict(re.findall(r"^(\w+)\s+(\d+)$", plan, re.M)) == counts
