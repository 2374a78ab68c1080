"""dice_core.planning: what a run makes of a dataset and a configuration, without the workflow engine."""

import copy
from pathlib import Path

import pytest
import yaml

from dice_core import planning, settings
from dice_core.manifest import parse_manifest
from dice_core.simulation import dataset_layout

from conftest import REPO, small_config

SCHEMA = settings.config_schema(REPO / "workflow" / "schemas" / "config.schema.yaml")
CONFIG = settings.with_defaults(yaml.safe_load((REPO / "config" / "config.yaml").read_text()), SCHEMA)


def plan(document=None, **config):
    layout = document if document is not None else dataset_layout(small_config())
    values = copy.deepcopy(CONFIG)
    for section, options in config.items():
        values[section] = {**values[section], **options} if isinstance(options, dict) else options
    return planning.Plan(parse_manifest(layout, "/data/bench/dataset.yaml"), values, "results/sim-test",
                         "results/sweeps")


def test_the_default_targets_are_every_stage_s_products_under_the_dataset_s_folder():
    targets = plan().default_targets()
    assert all(t.startswith("results/sim-test/") for t in targets) and len(targets) == len(set(targets))
    for expected in ("calibration/dark.nc", "calibration/prnu.nc", "calibration/prnu_difference_fiber_b.nc",
                     "metrology/H1H4.nc", "allan/V2V4.nc", "calibration/offsets_P24.nc",
                     "calibration/offsets_difference_P24.nc", "centroids/flat+metrology+width.nc",
                     "centroids/gaussian/raw.nc", "tables/accuracy.csv", "figures/procrustes_residuals.pdf"):
        assert f"results/sim-test/{expected}" in targets, expected
    assert "results/sim-test/centroids/fourier/raw.nc" not in targets  # the configured method has no folder
    with_pose = plan(astrometry={"superimposition": ["pose", "procrustes"]}).default_targets()
    assert set(with_pose) - set(targets) == {"results/sim-test/figures/pose_residuals.png",
                                             "results/sim-test/figures/pose_residuals.pdf"}


def test_what_a_dataset_lacks_is_skipped_and_said_once():
    layout = dataset_layout(small_config())
    del layout["flats"]
    layout["metrology"]["pairs"] = {}
    p = plan(layout)
    targets = p.default_targets()
    p.default_targets()  # asked again: said once
    assert not any("prnu" in t for t in targets) and "results/sim-test/centroids/raw.nc" in targets
    assert p.skipped == [f"skipping PRNU: {p.manifest.path} has no flats section",
                         "skipping deprojection: the dataset names no pair of baselines",
                         "skipping centroid mode flat: the dataset has no flat field",
                         "skipping centroid mode metrology: the dataset names no pair of metrology baselines",
                         "skipping centroid mode flat+metrology: the dataset has no flat field",
                         "skipping centroid mode flat+metrology+width: the dataset has no flat field"]
    # every mode (the default) on a dataset that states no wavelength: the chromatic mode left out unsaid


@pytest.mark.parametrize("config, expected", [
    ({"centroids": {"pair": "P99"}}, "config centroids.pair 'P99' is not a pair of /data/bench/dataset.yaml"),
    ({"centroids": {"half_size": 30}}, "detector.science_area holds 37 row(s) x 40 col(s), too few for the 61x61"),
])
def test_a_plan_the_dataset_cannot_hold_is_one_line(config, expected):
    with pytest.raises(planning.PlanningError, match=expected.replace("(", r"\(").replace(")", r"\)")):
        plan(**config).default_targets()


@pytest.mark.parametrize("section, name, other", [("pairs", "difference_P24", "P24"),
                                                   ("flats", "difference_fiber_b", "fiber_b")])
def test_names_that_would_make_two_products_one_file_are_refused(section, name, other):
    """A pair named difference_P24 beside P24: offsets_difference_P24.nc would be both (a 12-line
    AmbiguousRuleException from Snakemake); a flat difference_fiber_b beside fiber_b likewise."""
    layout = dataset_layout(small_config())
    entries = layout["metrology"]["pairs"] if section == "pairs" else layout["flats"]
    entries[name] = copy.deepcopy(entries[other])
    with pytest.raises(planning.PlanningError) as info:
        plan(layout).check_names()
    assert f"'{name}'" in str(info.value) and str(info.value).endswith("rename it")
    plan().check_names()
    alone = dataset_layout(small_config())  # alone, a pair difference_P24 would be read as a difference
    alone["metrology"]["pairs"] = {"difference_P24": alone["metrology"]["pairs"]["P24"]}
    with pytest.raises(planning.PlanningError, match="'difference_P24' would make calibration/offsets_difference_P24"):
        plan(alone).check_names()


def test_sweep_points_are_folders_as_snakemake_s_paramspace_names_them():
    """The folders of the existing results stay valid: the same names as Paramspace gave them (pandas typing
    included: an integer beside a float in one column is spelt as a float)."""
    from pandas import DataFrame
    from snakemake.utils import Paramspace

    specs = {**CONFIG["sweeps"], "mixed": {"study": "offset_bias", "parameter": "detector.prnu_rms",
                                           "values": [0, 2.5e-3, 1]},
             "words": {"study": "error_propagation", "grid": {"source": ["prnu", "read"], "seed": [1, 2]}}}
    for name, spec in specs.items():
        sweep = planning.plan_sweep(name, spec)
        columns = sweep.columns
        frame = DataFrame([{c: planning.folder_value(point[k]) for c, k in columns.items()} for point in
                           ([{k: v for k, v in p.items()} for p in _raw_points(spec)])])
        assert list(sweep.folders) == list(Paramspace(frame, single_wildcard="point").instance_patterns), name
    assert planning.plan_sweep("mixed", specs["mixed"]).points[0] == {"detector.prnu_rms": 0.0}


def _raw_points(spec):
    import itertools

    if "points" in spec:
        return spec["points"]
    if "grid" in spec:
        return [dict(zip(spec["grid"], c)) for c in itertools.product(*spec["grid"].values())]
    return [{spec["parameter"]: v} for v in spec["values"]]


@pytest.mark.parametrize("spec, expected", [
    ({"study": "offset_bias", "parameter": "source", "values": ["../../x"]}, "cannot name a point's folder"),
    ({"study": "offset_bias", "parameter": "source", "values": ["{x}"]}, "cannot name a point's folder"),
    ({"study": "offset_bias", "parameter": "a", "values": [1, 1]}, "a point is listed twice"),
    ({"study": "offset_bias", "points": [{"a": 1}, {"b": 2}]}, "every point must set the same parameters"),
    ({"study": "offset_bias", "points": [{"x.a": 1, "y.a": 2}]}, "share a last name"),
    ({"study": "offset_bias", "parameter": "a", "values": [[1, 2]]}, "lists, e.g. of centroids.modes, only in a"),
    ({"study": "offset_bias", "parameter": "a", "values": [1, None]}, "null, which names no folder"),
])
def test_a_sweep_that_cannot_be_planned_is_one_line_naming_it(spec, expected):
    with pytest.raises(planning.PlanningError, match=f"^config sweeps.s.*{expected}"):
        planning.plan_sweep("s", spec)


def test_a_reduction_point_is_the_run_s_config_with_its_keys_set():
    sweep = planning.plan_sweep("r", {"study": "reduction", "parameter": "centroids.half_size", "values": [4, 5]})
    point = planning.reduction_point_config(CONFIG, sweep, index=0, simulated=True, raw="results/sim-ci/raw",
                                            sweeps_root="results/sweeps")
    assert point["centroids"]["half_size"] == 4 and point["raw"] == "results/sim-ci/raw"
    assert point["results"] == "results/sweeps/r/half_size~4" and "r" not in point["sweeps"]
    assert planning.module_name("r", "half_size~4") != planning.module_name("r", "half_size~5")
    with pytest.raises(planning.PlanningError, match="need a simulation preset"):
        simulated = planning.plan_sweep("r", {"study": "reduction", "parameter": "simulation.seed", "values": [1]})
        planning.reduction_point_config(CONFIG, simulated, index=0, simulated=False, raw="x",
                                        sweeps_root="results/sweeps")


# ------------------------------------------------------------------ several wavelengths (format 1.2, issue 26)

def chromatic_layout(**stars):
    """small_config's bench with lasers at 633 and 450 nm (both pairs each) and a laser flat at 450 nm."""
    return dataset_layout(small_config(metrology={"wavelengths": [633e-9, 450e-9]}, flats={"wavelengths": [450e-9]},
                                       stars=stars))


def test_a_single_wavelength_dataset_plans_what_it_did():
    """No calibration across wavelength and no chromatic mode; the PRF widths of every baseline and the
    reference flat for every baseline's gauge, as before format 1.2. With every mode (the default) nothing is
    said of the chromatic one (every run of such a dataset would say it); asked for by name, it is skipped and
    said why."""
    p = plan()
    targets = p.default_targets()
    assert not any("chromatic" in t for t in targets)
    assert p.prf_baselines() == ["H1H4", "V1V4", "H2H4", "V2V4"]
    assert all(p.prnu_for_metrology(b) == ["results/sim-test/calibration/prnu.nc"] for b in p.manifest.baselines)
    assert not any("chromatic" in line for line in p.skipped), p.skipped
    asked = plan(centroids={"modes": ["flat+metrology", "flat+metrology+chromatic"]})
    assert "results/sim-test/centroids/flat+metrology.nc" in asked.default_targets()
    assert asked.skipped == [
        "skipping centroid mode flat+metrology+chromatic: no calibration across wavelength: /data/bench/"
        "dataset.yaml has its pairs at no stated wavelength (format 1.2 gives each baseline its own)"]


def test_several_wavelengths_plan_the_chromatic_calibration_and_mode():
    p = plan(chromatic_layout(spectrum="warm"))
    targets = p.default_targets()
    assert {"results/sim-test/calibration/chromatic.nc", "results/sim-test/figures/chromatic.png",
            "results/sim-test/centroids/flat+metrology+chromatic.nc"} <= set(targets)
    # each wavelength's pairs reduced as a single wavelength's are
    assert {"results/sim-test/calibration/offsets_P14_450.nc", "results/sim-test/metrology/V2V4_450.nc"} <= set(targets)
    assert p.centroid_calibrations("flat+metrology+chromatic")["chromatic"] == "results/sim-test/calibration/chromatic.nc"
    inputs = p.chromatic_inputs()
    assert inputs["offsets"] == ["results/sim-test/calibration/offsets_P14.nc",
                                 "results/sim-test/calibration/offsets_P14_450.nc"]  # each wavelength's reference pair
    assert len(inputs["metrology"]) == 8 and inputs["flats"] == ["results/sim-test/calibration/flats/prnu_laser_450.nc"]
    # the PRF widths of the reference wavelength's baselines; a 450 nm baseline's gauge takes the 450 nm flat
    assert p.prf_baselines() == ["H1H4", "V1V4", "H2H4", "V2V4"]
    assert p.prnu_for_metrology("H1H4_450") == ["results/sim-test/calibration/flats/prnu_laser_450.nc"]
    assert p.prnu_for_metrology("H1H4") == ["results/sim-test/calibration/prnu.nc"]


def test_pairs_and_flats_are_compared_within_their_own_light():
    """A difference's photon-noise check needs the true offsets (or PRNU) to cancel: each pair is compared
    with its wavelength's first pair, each flat with the first of its own light, never across wavelengths."""
    p = plan(chromatic_layout(spectrum="warm"))
    assert p.compared_pairs() == {"P24": "P14", "P24_450": "P14_450"}
    assert p.compared_flats() == {"fiber_b": "fiber_a"}  # laser_450 is its light's first: no difference
    assert p.prnu_compared_with("fiber_b") == "results/sim-test/calibration/prnu.nc"
    targets = p.default_targets()
    assert "results/sim-test/calibration/offsets_difference_P24_450.nc" in targets
    assert not any("offsets_difference_P14_450" in t or "prnu_difference_laser_450" in t for t in targets)
    single = plan()  # one wavelength: the reference pair and flat, as before format 1.2
    assert single.compared_pairs() == {"P24": "P14"} and single.compared_flats() == {"fiber_b": "fiber_a"}


def test_wavelengths_and_spectra_the_model_cannot_use_are_said_in_one_line():
    """The per-pixel model covers silicon's 380-1000 nm: a laser or a spectrum beyond it skips the chromatic
    calibration or mode, saying why; a configured spectrum that cannot be one (nm for m) is refused."""
    layout = chromatic_layout(spectrum="warm")
    for baseline in ("H1H4_450", "V1V4_450", "H2H4_450", "V2V4_450"):
        layout["metrology"]["baselines"][baseline]["wavelength"] = 1064e-9
    p = plan(layout)
    assert p.chromatic_unavailable().endswith("pair P14_450's wavelength 1.064e-06 m is outside the per-pixel model's "
                                              "380-1000 nm (silicon's absorption table)")
    assert not any("chromatic" in t for t in p.default_targets())
    layout = chromatic_layout(spectrum="warm")
    layout["stars"]["spectrum"]["wavelength"][0] = 300e-9
    p = plan(layout)
    assert "flat+metrology+chromatic" not in p.centroid_modes()
    assert any("stars.spectrum wavelength 3e-07 m is outside the per-pixel model's" in line for line in p.skipped)
    with pytest.raises(planning.PlanningError, match=r"^config centroids.spectrum: wavelength 400 m is outside .* "
                                                     r"\(wavelengths are in m\)$"):
        plan(chromatic_layout(), centroids={"spectrum": {"wavelength": [400, 800], "weight": [1, 1]}}).centroid_modes()


def test_the_chromatic_mode_needs_a_spectrum_of_the_stars():
    p = plan(chromatic_layout())
    assert "flat+metrology+chromatic" not in p.centroid_modes()
    assert any("no spectrum of the stars" in line and "centroids.spectrum is null" in line for line in p.skipped)
    assert "flat+metrology+chromatic" in plan(chromatic_layout(), centroids={"spectrum": "cool"}).centroid_modes()


def test_the_reproduction_report_has_the_chromatic_study_s_page():
    pages = planning.paper_pdf_pages(plan(), REPO / "workflow" / "report")
    assert ("results/sweeps/chromatic/chromatic.png", str(REPO / "workflow" / "report" / "chromatic_study.rst")) in pages
    assert all(Path(caption).is_file() for _, caption in pages)
