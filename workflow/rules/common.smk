# Plumbing of the workflow: config validation, the dataset to reduce, input
# functions and the code versions that make a dice_core change re-run what it
# affects. No numerics here: they live in dice_core.

import ast
import hashlib
import itertools
import json
import os
import re
import sys
from importlib import util
from pathlib import Path

from pandas import DataFrame
from snakemake.utils import Paramspace, validate

from dice_core import DatasetError, simulation, superimposition, yamlfile
from dice_core.centroids import MODE_NEEDS, science_area_problem
from dice_core.io import file_groups, write_text
from dice_core.manifest import load_manifest, parse_manifest
from dice_core.overrides import apply_dotted


def fail(message):
    """Stop the run with ``message``, one ``dice:`` line per line of it, and exit status 1: a problem of the
    configuration or the dataset, said before any job runs. A WorkflowError would wrap it in Snakemake's
    header and the file and line of this workflow, which are not the user's problem."""
    print("\n".join(f"dice: {line}" for line in str(message).splitlines()), file=sys.stderr)
    raise SystemExit(1)


def check_config_files(paths):
    """Refuse a configuration file that gives one key twice (Snakemake's YAML reader keeps the second)."""
    for path in paths:
        try:
            yamlfile.read(path)
        except DatasetError as exc:
            fail(exc)


def check_config(values, schema_path):
    """Check the configuration against its schema, each problem in one line naming the key.

    An unknown key is named with the nearest valid key (difflib) and the valid keys at its level,
    instead of the schema in full that Snakemake's validate prints.
    """
    import difflib

    import jsonschema
    import yaml

    schema = yaml.safe_load(Path(schema_path).read_text())
    validator = jsonschema.validators.validator_for(schema)(schema)
    problems = []
    for error in sorted(validator.iter_errors(values), key=lambda e: [str(p) for p in e.absolute_path]):
        where = "".join(f"{part}." for part in error.absolute_path)
        if error.validator == "additionalProperties" and error.validator_value is False:
            known = list(error.schema.get("properties", {}))
            for key in sorted(set(error.instance) - set(known)):
                near = difflib.get_close_matches(str(key), known, n=1, cutoff=0.6)
                hint = f"; did you mean {where}{near[0]}?" if near else ""
                problems.append(
                    f"config {where}{key}: unknown key{hint} (keys of {where.rstrip('.') or 'the config'}: "
                    f"{', '.join(known)})"
                )
        else:
            message = error.message if len(error.message) <= 200 else f"{error.message[:200]}..."
            problems.append(f"config {where.rstrip('.') or '(top level)'}: {message}")
    if problems:
        fail("\n".join(problems))


check_config_files(workflow.configfiles)
check_config(config, Path(workflow.basedir) / "workflow" / "schemas" / "config.schema.yaml")
validate(config, schema="../schemas/config.schema.yaml")  # passes now; sets the defaults

PRESETS = Path(workflow.basedir) / "config" / "presets"


def local_path(path):
    """A path relative to the working directory when it lies below it.

    Inputs must be spelt as the rules that make them spell their outputs, and
    those are relative; files outside the working directory stay absolute.
    """
    path = Path(path).resolve()
    cwd = Path.cwd().resolve()
    return str(path.relative_to(cwd)) if path.is_relative_to(cwd) else str(path)


def load_dataset(value):
    """(manifest, simulation config or None) for config['dataset']: a preset name or a manifest path."""
    if value.endswith((".yaml", ".yml")) or os.sep in value:
        try:
            return load_manifest(value), None
        except DatasetError as exc:
            fail(f"config dataset: {exc}")
    preset = PRESETS / f"{value}.yaml"
    if not preset.is_file():
        known = sorted(p.stem for p in PRESETS.glob("*.yaml"))
        fail(f"config dataset={value!r} is neither a manifest path (*.yaml) nor a simulation preset {known}")
    try:
        sim = simulation.load_preset(preset, overrides=config.get("simulation") or {})
        raw = config.get("raw") or Path(config["results"]) / sim.name / "raw"
        return parse_manifest(simulation.dataset_layout(sim), Path(raw) / "dataset.yaml"), sim
    except ValueError as exc:  # DatasetError included: a preset's name or keys
        fail(exc)


# The sweeps' folder beside the datasets' own: no dataset may be named after it.
SWEEPS_FOLDER = "sweeps"
MANIFEST, SIMULATION = load_dataset(str(config["dataset"]))
if MANIFEST.name == SWEEPS_FOLDER:
    fail(f"{MANIFEST.path}: manifest name {SWEEPS_FOLDER!r} is the results folder's sweeps folder; rename the dataset")
OUT = f"{config['results']}/{MANIFEST.name}"
# A sweep point of the reduction alone reads its dataset's raw files where the main run simulates them
# (config raw), instead of simulating them again.
RAW = local_path(config["raw"]) if config.get("raw") else f"{OUT}/raw"
SIMULATE = SIMULATION is not None and not config.get("raw")
MANIFEST_FILE = local_path(MANIFEST.path)
# Products record their inputs relative to the dataset's folder (the manifest's) and to the results folder,
# tried in that order, so that they hold no absolute path of this machine (dice_core.io.write_product).
ROOTS = {"dataset": local_path(MANIFEST.path.parent), "results": OUT}


wildcard_constraints:
    flat="|".join(map(re.escape, MANIFEST.flats)) or "(?!)",
    baseline="|".join(map(re.escape, MANIFEST.baselines)) or "(?!)",
    pair="|".join(map(re.escape, MANIFEST.pairs)) or "(?!)",
    position="|".join(str(p.index) for p in MANIFEST.positions) or "(?!)",
    mode="|".join(map(re.escape, MODE_NEEDS)),
    method="fourier|gaussian",


# One set for the run and the modules of its reduction sweep's points, which evaluate this file again with the
# same workflow object: a reason is said once, not once per point.
_SKIPPED = vars(workflow).setdefault("_dice_skipped", set())


def script_version(*names):
    """Hash of workflow/scripts/<name>.py for each name, passed as a param where a rule stands for steps whose
    scripts are not its own (Snakemake's code trigger sees a rule's own script only)."""
    digest = hashlib.sha256()
    for name in names:
        digest.update((Path(workflow.basedir) / "workflow" / "scripts" / f"{name}.py").read_bytes())
    return digest.hexdigest()[:16]


def skipped(what, why):
    """Say once what this dataset does not allow (the target functions are called more than once)."""
    message = f"dice: skipping {what}: {why}"
    if message not in _SKIPPED:
        _SKIPPED.add(message)
        print(message, file=sys.stderr)


def dice_core_imports(path):
    """Names of the dice_core modules a module's source imports, at its top or inside functions."""
    names = set()
    for node in ast.walk(ast.parse(Path(path).read_text())):
        if isinstance(node, ast.ImportFrom) and node.module == "dice_core":
            names |= {alias.name for alias in node.names}  # modules and other names; the caller keeps modules
        elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith("dice_core."):
            names.add(node.module.split(".")[1])
        elif isinstance(node, ast.Import):
            names |= {alias.name.split(".")[1] for alias in node.names if alias.name.startswith("dice_core.")}
    return names


def code_version(*modules):
    """Hash of the dice_core modules a step runs, with every module they import in turn, passed as a param.

    Snakemake re-runs a job when its params change, so editing a module
    re-runs the jobs that use it, directly or through another module, and
    only those. The package's ``__init__`` always counts.
    """
    package = Path(util.find_spec("dice_core").origin).parent
    todo, closure = ["__init__", *modules], set()
    while todo:
        name = todo.pop()
        if name in closure or not (package / f"{name}.py").is_file():  # a class or function, not a module
            continue
        closure.add(name)
        todo += sorted(dice_core_imports(package / f"{name}.py"))
    digest = hashlib.sha256()
    for name in sorted(closure):
        digest.update((package / f"{name}.py").read_bytes())
    return digest.hexdigest()[:16]


def acquisition_files(acquisition):
    return [local_path(f) for f in acquisition.files]


def flat_files(wildcards):
    if wildcards.flat not in MANIFEST.flats:
        fail(f"no flat named {wildcards.flat!r} in {MANIFEST.path}")
    return acquisition_files(MANIFEST.flats[wildcards.flat])


def figure_pair(stem):
    return {"png": f"{OUT}/figures/{stem}.png", "pdf": f"{OUT}/figures/{stem}.pdf"}


def calibration_targets():
    """Products and figures of the dark and PRNU stages that this dataset allows."""
    targets = []
    if MANIFEST.dark is None:
        skipped("dark and PRNU", f"{MANIFEST.path} has no dark section")
        return targets
    targets += [f"{OUT}/calibration/dark.nc", *figure_pair("dark").values(), *figure_pair("dark_noise").values()]
    if not MANIFEST.flats:
        skipped("PRNU", f"{MANIFEST.path} has no flats section")
        return targets
    targets += [f"{OUT}/calibration/prnu.nc", f"{OUT}/calibration/bad_pixels.nc"]
    for flat in MANIFEST.flats:
        targets += figure_pair(f"prnu_{flat}").values()
    others = list(MANIFEST.flats)[1:]
    for flat in others:
        targets += [f"{OUT}/calibration/prnu_difference_{flat}.nc", *figure_pair(f"prnu_difference_{flat}").values()]
    if not others:
        skipped("PRNU difference", "the dataset has a single flat")
    return targets


def baseline_files(wildcards):
    return acquisition_files(MANIFEST.baselines[wildcards.baseline])


def prnu_for_metrology(wildcards):
    """The reference PRNU, which tells the fringe solution the intensity map from the fringe."""
    if config["metrology"]["use_flat"] and MANIFEST.flats:
        return [f"{OUT}/calibration/prnu.nc"]
    return []


def bad_pixel_mask(wildcards=None):
    """The bad-pixel mask, which every stage that reads pixels leaves its flagged pixels out by, if the
    dataset allows one (a dark and a flat)."""
    if MANIFEST.dark and MANIFEST.flats:
        return [f"{OUT}/calibration/bad_pixels.nc"]
    return []


def pair_baselines(wildcards):
    return list(MANIFEST.pairs[wildcards.pair])


def metrology_unavailable():
    """Why this dataset's metrology cannot be reduced, or None."""
    if not MANIFEST.baselines:
        return f"{MANIFEST.path} has no metrology section"
    if MANIFEST.dark is None:
        return f"{MANIFEST.path} has no dark to subtract"
    return None


def metrology_products(wildcards=None):
    """Every baseline's metrology product (the PRF widths use them all)."""
    return [f"{OUT}/metrology/{baseline}.nc" for baseline in MANIFEST.baselines]


def metrology_targets():
    """Products and figures of the metrology stage that this dataset allows."""
    why = metrology_unavailable()
    if why is not None:
        skipped("metrology", why)
        return []
    targets = []
    for baseline in MANIFEST.baselines:
        targets += [
            f"{OUT}/metrology/{baseline}.nc",
            *figure_pair(f"metrology_{baseline}").values(),
            f"{OUT}/allan/{baseline}.nc",
            *figure_pair(f"allan_{baseline}").values(),
        ]
    targets += [f"{OUT}/calibration/prf.nc", *figure_pair("prf").values()]
    for pair in MANIFEST.pairs:
        targets += [f"{OUT}/calibration/offsets_{pair}.nc", *figure_pair(f"offsets_{pair}").values()]
    for pair in list(MANIFEST.pairs)[1:]:
        targets += [
            f"{OUT}/calibration/offsets_difference_{pair}.nc",
            *figure_pair(f"offsets_difference_{pair}").values(),
        ]
    if not MANIFEST.pairs:
        skipped("deprojection", "the dataset names no pair of baselines")
    return targets


def centroid_pair():
    """The metrology pair whose offsets the metrology modes use."""
    pair = config["centroids"]["pair"] or MANIFEST.reference_pair
    if pair is not None and pair not in MANIFEST.pairs:
        pairs = ", ".join(MANIFEST.pairs) or "none"
        fail(f"config centroids.pair {pair!r} is not a pair of {MANIFEST.path} (pairs: {pairs})")
    return pair


def manifest_position(wildcards):
    """The manifest's star position of the {position} wildcard (its index)."""
    return next(p for p in MANIFEST.positions if str(p.index) == wildcards.position)


def position_files(wildcards):
    return acquisition_files(manifest_position(wildcards).acquisition)


def position_stacks(wildcards):
    """Every position's stars/<index>.nc, in acquisition order."""
    return [f"{OUT}/stars/{p.index}.nc" for p in MANIFEST.positions]


def centroid_calibrations(wildcards):
    """The calibration products a mode needs (dice_core.centroids.MODE_NEEDS): the reference PRNU, the
    pair's offsets, the PRF widths; the bad-pixel mask."""
    inputs = {"bad_pixels": bad_pixel_mask()} if bad_pixel_mask() else {}
    needs = MODE_NEEDS[wildcards.mode]
    if "flat" in needs:
        inputs["prnu"] = f"{OUT}/calibration/prnu.nc"
    if "offsets" in needs:
        inputs["offsets"] = f"{OUT}/calibration/offsets_{centroid_pair()}.nc"
    if "widths" in needs:
        inputs["prf"] = f"{OUT}/calibration/prf.nc"
    return inputs


def centroid_options(wildcards):
    """What a product depends on: the method and the window options, not the list of modes or methods,
    so that adding an entry to either list runs only the new jobs (the batches are the stacks')."""
    options = {k: v for k, v in config["centroids"].items() if k not in ("modes", "methods", "batches")}
    return {**options, "method": getattr(wildcards, "method", config["centroids"]["method"])}


def other_methods():
    """The centroid methods besides centroids.method, each under centroids/<method>/: in the order of
    centroids.methods, whose order decides nothing else."""
    return [m for m in config["centroids"]["methods"] if m != config["centroids"]["method"]]


def centroid_targets():
    """Centroid products and figures of the configured modes that this dataset allows."""
    if not MANIFEST.positions:
        skipped("centroids", f"{MANIFEST.path} has no star positions")
        return []
    if MANIFEST.dark is None:
        skipped("centroids", f"{MANIFEST.path} has no dark to subtract")
        return []
    if (problem := science_area_problem(MANIFEST.detector, config["centroids"]["half_size"])) is not None:
        fail(f"{MANIFEST.path}: {problem}")
    targets = []
    for mode in config["centroids"]["modes"]:
        needs = MODE_NEEDS[mode]
        if "flat" in needs and not MANIFEST.flats:
            skipped(f"centroid mode {mode}", "the dataset has no flat field")
            continue
        if "offsets" in needs and centroid_pair() is None:
            skipped(f"centroid mode {mode}", "the dataset names no pair of metrology baselines")
            continue
        if needs & {"offsets", "widths"} and metrology_unavailable() is not None:
            skipped(f"centroid mode {mode}", f"the metrology is not reduced ({metrology_unavailable()})")
            continue
        targets += [f"{OUT}/centroids/{mode}.nc", *figure_pair(f"centroids_{mode}").values()]
        targets += [f"{OUT}/centroids/{method}/{mode}.nc" for method in other_methods()]
    return targets


def astrometry_targets():
    """The accuracy table of the centroid modes this dataset allows, and its figure."""
    if not centroid_targets():
        return []
    return [
        f"{OUT}/tables/accuracy.csv",
        f"{OUT}/tables/accuracy.tex",
        *figure_pair("procrustes_residuals").values(),
        *figure_pair("barycentre_residuals").values(),
        *(path for model in extra_superimpositions() for path in figure_pair(f"{model}_residuals").values()),
    ]


def extra_superimpositions():
    """The superimpositions configured besides Procrustes (which always runs): projective, pose."""
    return superimposition.configured_superimpositions(config["astrometry"].get("superimposition", "procrustes"))[1:]


def centroid_products(wildcards):
    """Every centroid product of the sweep: each allowed mode with each method."""
    return [t for t in centroid_targets() if t.endswith(".nc")]


# --------------------------------------------------------------------------- sweeps and the paper target


SWEEP_ROOT = f"{config['results']}/{SWEEPS_FOLDER}"


SWEEP_VALUES = {}  # sweep -> its points as {dotted key: value}, list values included (reduction sweeps)


def folder_value(value):
    """How a point's value is spelt in its folder name: itself, or a list's items joined by commas (a short
    hash where an item is not a plain word or number), so that a list is one folder of its own."""
    if not isinstance(value, (list, dict)):
        return value
    items = value if isinstance(value, list) else None
    if items is not None and all(
        isinstance(v, (str, int, float)) and re.fullmatch(r"[A-Za-z0-9_.+-]+", str(v)) for v in items
    ):
        return ",".join(map(str, items)) or "none"
    return f"h{hashlib.sha256(json.dumps(value, sort_keys=True).encode()).hexdigest()[:10]}"


def sweep_space(name, spec):
    """(Paramspace with one wildcard 'point', column -> parameter key) of a configured sweep; its points'
    values in SWEEP_VALUES[name]."""
    if "points" in spec:
        points = [dict(p) for p in spec["points"]]
    elif "grid" in spec:  # every combination, the first parameter varying slowest
        keys = list(spec["grid"])
        points = [dict(zip(keys, combination)) for combination in itertools.product(*spec["grid"].values())]
    else:
        points = [{spec["parameter"]: value} for value in spec["values"]]
    keys = sorted({key for p in points for key in p})
    if any(set(p) != set(keys) for p in points):
        fail(f"config sweeps.{name}.points: every point must set the same parameters {keys}")
    columns = {key.rsplit(".", 1)[-1]: key for key in keys}  # folder names: the key's last part
    if len(columns) != len(keys):
        fail(f"config sweeps.{name}: parameters {keys} share a last name; folders would clash")
    if spec["study"] != "reduction" and any(isinstance(v, (list, dict)) for p in points for v in p.values()):
        fail(
            f"config sweeps.{name}: a parameter's value must be a number, a string or a boolean "
            "(one folder per point; lists, e.g. of centroids.modes, only in a reduction sweep)"
        )
    frame = DataFrame([{column: folder_value(p[key]) for column, key in columns.items()} for p in points])
    if frame.duplicated().any():
        fail(f"config sweeps.{name}: a point is listed twice")
    SWEEP_VALUES[name] = points
    return Paramspace(frame, single_wildcard="point"), columns


SWEEPS = {name: (spec, *sweep_space(name, spec)) for name, spec in config.get("sweeps", {}).items()}
REDUCTION_SWEEPS = [name for name, (spec, *_) in SWEEPS.items() if spec["study"] == "reduction"]
STUDY_SWEEPS = [name for name in SWEEPS if name not in REDUCTION_SWEEPS]


def sweep_points(name):
    """The point products of a configured sweep, in the config's order."""
    if name not in SWEEPS:
        fail(f"no sweep named {name!r} in config sweeps (sweeps: {', '.join(SWEEPS) or 'none'})")
    space = SWEEPS[name][1]
    return [f"{SWEEP_ROOT}/{name}/{point}/point.nc" for point in space.instance_patterns]


def point_parameters(wildcards):
    """The {point} wildcard as the study's parameters (dotted bench keys or option names)."""
    spec, space, columns = SWEEPS[wildcards.sweep]
    values = space.instance(wildcards)
    return {columns[column]: (value.item() if hasattr(value, "item") else value) for column, value in values.items()}


def paper_sweep(study):
    """The sweep that config paper.<study> names, checked to run that study."""
    name = config["paper"][study]
    if name not in SWEEPS or SWEEPS[name][0]["study"] != study:
        fail(f"config paper.{study}: {name!r} is not a sweep of study {study} in config sweeps")
    return name


def comparison_inputs(wildcards=None):
    """What the comparison reads: the studies, and this dataset's accuracy table and Allan products."""
    inputs = {
        "offset_bias": sweep_points(paper_sweep("offset_bias")),
        "error_propagation": f"{OUT}/tables/error_propagation.csv",
        "deflation": f"{OUT}/tables/procrustes_deflation.csv",
    }
    if astrometry_targets():
        inputs["accuracy"] = f"{OUT}/tables/accuracy.csv"
    if metrology_unavailable() is None:
        inputs["allan"] = [f"{OUT}/allan/{baseline}.nc" for baseline in MANIFEST.baselines]
    return inputs


def sweep_instances(name):
    """[(parameters by their dotted keys, the point's folder)] of a configured sweep, in order."""
    spec, space, columns = SWEEPS[name]
    return [
        ({key: (v.item() if hasattr(v, "item") else v) for key, v in point.items()}, folder)
        for point, folder in zip(SWEEP_VALUES[name], space.instance_patterns)
    ]


def reduction_point_config(name, point, folder):
    """The workflow config of one point of a reduction sweep: the run's config with the point's keys set.

    ``simulation.<key>`` sets a key of the simulation preset (the dataset is simulated again, in the point's
    folder); any other dotted key sets the reduction's config, and the point then reads the run's raw files.
    """
    spec = SWEEPS[name][0]
    reserved = [k for k in point if k.split(".")[0] in ("dataset", "raw", "results", "sweeps", "paper")]
    if reserved or spec.get("bench") or spec.get("options"):
        fail(
            f"config sweeps.{name}: a reduction sweep varies the reduction's config or "
            f"simulation.<key>, not {reserved or 'bench or options'}"
        )
    simulated = {k.split(".", 1)[1]: v for k, v in point.items() if k.startswith("simulation.")}
    reduction = {k: v for k, v in point.items() if not k.startswith("simulation.")}
    if simulated and SIMULATION is None:
        fail(f"config sweeps.{name}: simulation.* parameters need a simulation preset as the dataset")
    try:
        point_config = apply_dotted({k: v for k, v in config.items() if k != "sweeps"}, reduction, what="config")
    except (KeyError, ValueError) as exc:
        fail(f"config sweeps.{name}: {exc.args[0]}")
    point_config["sweeps"] = {n: s for n, (s, *_) in SWEEPS.items() if s["study"] != "reduction"}
    point_config["simulation"] = {**(config.get("simulation") or {}), **simulated}
    point_config["results"] = f"{SWEEP_ROOT}/{name}/{folder}"
    point_config["raw"] = None if simulated else RAW  # a simulated point's own raw files, in its folder
    return point_config


def point_dataset_name(point_config):
    """The name of a reduction point's dataset: the run's, or, where the point sets simulation.* keys, that of
    the preset with the point's overrides (simulation.load_preset names it by their hash)."""
    if SIMULATION is None or point_config["simulation"] == (config.get("simulation") or {}):
        return MANIFEST.name
    return simulation.load_preset(PRESETS / f"{config['dataset']}.yaml", overrides=point_config["simulation"]).name


def reduction_point_tables(wildcards):
    """Each point's tables/accuracy.csv of a reduction sweep, in the config's order."""
    name = wildcards.sweep
    datasets = {
        folder: point_dataset_name(REDUCTION_CONFIGS[module_name(name, folder)]) for _, folder in sweep_instances(name)
    }
    return [f"{SWEEP_ROOT}/{name}/{folder}/{dataset}/tables/accuracy.csv" for folder, dataset in datasets.items()]


def module_name(sweep, folder):
    """The Snakemake module of a reduction sweep's point, named by the point (its folder) and not by its place
    in the list, so that removing a point renames no other's rules."""
    words = re.sub(r"\W+", "_", f"{sweep}_{folder}").strip("_")[:60]
    return f"sweep_{words}_{hashlib.sha256(folder.encode()).hexdigest()[:6]}"


def paper_pdf_pages():
    """(figure, its caption file) of the PDF reproduction report: the paper's simulations, then this dataset's
    figures that the paper shows, those the dataset allows."""
    captions = Path(workflow.basedir) / "workflow" / "report"
    pages = [
        (f"{OUT}/figures/{stem}.png", str(captions / f"{stem}.rst"))
        for stem in ("paper_comparison", "offset_bias", "error_propagation")
    ]
    if metrology_unavailable() is None:
        first = next(iter(MANIFEST.baselines))
        pages += [
            (f"{OUT}/figures/metrology_{first}.png", str(captions / "metrology.rst")),
            (f"{OUT}/figures/allan_{first}.png", str(captions / "allan.rst")),
        ]
        if MANIFEST.pairs:
            pages.append((f"{OUT}/figures/offsets_{next(iter(MANIFEST.pairs))}.png", str(captions / "offsets.rst")))
    if astrometry_targets():
        modes = [m for m in ("flat+metrology", "raw") if f"{OUT}/figures/centroids_{m}.png" in centroid_targets()]
        pages += [(f"{OUT}/figures/centroids_{m}.png", str(captions / "centroids.rst")) for m in modes[:1]]
        pages += [
            (f"{OUT}/figures/barycentre_residuals.png", str(captions / "barycentre_residuals.rst")),
            (f"{OUT}/figures/procrustes_residuals.png", str(captions / "procrustes_residuals.rst")),
        ]
    return pages


# --------------------------------------------------------------------------- cluster resources
# Each rule's resources block (mem_mb, runtime) comes from step_resources: the measured cost of its step
# (dice_core.resources) applied to the job's share of the dataset. threads stay each rule's threads:
# directive (2 worker processes for the fits and the Allan deviations, 1 elsewhere).

import functools

from astropy.io import fits

from dice_core import resources as dice_resources

SIM_FRAMES = (
    {rel: stop - start for rel, (_, _, start, stop) in simulation.file_jobs(SIMULATION).items()}
    if SIMULATION is not None
    else {}
)


@functools.cache
def file_frames(path):
    """Frames of a raw file: the simulation's plan where it simulates the file (it may not exist yet), else
    NAXIS3 of the file's header."""
    path = Path(path).resolve()
    relative = (
        path.relative_to(MANIFEST.path.parent.resolve())
        if path.is_relative_to(MANIFEST.path.parent.resolve())
        else None
    )
    if relative is not None and relative.as_posix() in SIM_FRAMES:
        return SIM_FRAMES[relative.as_posix()]
    try:
        return int(fits.getheader(path).get("NAXIS3", 1))
    except (OSError, ValueError, IndexError) as exc:  # astropy's errors of a file that is not FITS
        named_by = next((a.label for a in MANIFEST.acquisitions() if path in a.files), "an acquisition")
        fail(f"{path}: not a readable FITS file ({' '.join(str(exc).split())}); named by {named_by} in {MANIFEST.path}")


def acquisition_frames(acquisition):
    return sum(file_frames(f) for f in acquisition.files)


# Every raw file's header read now, while the workflow is read: a file that is not FITS is then said in one
# line, before the jobs are planned (the resources of a job read it, where an error is Snakemake's traceback).
for _file in MANIFEST.all_files():
    file_frames(_file)


def part_files(wildcards):
    """The files of part ``wildcards.part`` of a split fit of ``wildcards.baseline``: the group of whole files
    dice_core.io.FrameStream.split gives the part (none for a part beyond the groups)."""
    files = acquisition_files(MANIFEST.baselines[wildcards.baseline])
    groups = file_groups([file_frames(f) for f in files], config["metrology"]["parts"])
    part = int(wildcards.part)
    return files[slice(*groups[part])] if part < len(groups) else []


def job_data(step, wildcards):
    """{frames, positions} a job of a step reads (or writes, for the simulation)."""
    positions = len(MANIFEST.positions)
    if step == "simulate_file":
        return {"frames": SIM_FRAMES[f"{wildcards.relpath}.fits"]}
    if step == "simulate_truth":
        return {"frames": sum(SIM_FRAMES.values()), "positions": positions}
    if step == "measure_dark":
        return {"frames": acquisition_frames(MANIFEST.dark) if MANIFEST.dark else 0}
    if step == "measure_prnu":
        return {"frames": acquisition_frames(MANIFEST.flats[wildcards.flat])}
    if step in ("fit_fringes", "allan_deviation", "fit_reduce", "fit_finish"):
        return {"frames": acquisition_frames(MANIFEST.baselines[wildcards.baseline])}
    if step == "fit_part":  # its own files' frames only (none for a part beyond the groups of files)
        return {"frames": sum(file_frames(f) for f in part_files(wildcards))}
    if step == "fit_start":  # the first chunk only
        return {"frames": 0}
    if step == "stack_position":
        return {"frames": acquisition_frames(manifest_position(wildcards).acquisition)}
    return {"positions": positions}


def step_resources(step):
    """A rule's resources block, ``resources: **step_resources("<rule>")``: mem_mb (MB) and runtime (minutes)
    of each job from its step's measured cost and the job's data, times the attempt on a retry."""
    pixels = MANIFEST.detector.shape[0] * MANIFEST.detector.shape[1]

    def needs(wildcards, attempt):
        return dice_resources.job_resources(step, pixels=pixels, **job_data(step, wildcards), attempt=attempt)

    return {
        "mem_mb": lambda wildcards, attempt: needs(wildcards, attempt)["mem_mb"],
        "runtime": lambda wildcards, attempt: needs(wildcards, attempt)["runtime"],
    }
