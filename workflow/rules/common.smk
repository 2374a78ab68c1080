# Plumbing of the workflow: the configuration checked, the dataset to reduce, what a rule hands its step. What
# the run makes and each step reads is said in dice_core (planning, steps, products, settings, resources):
# nothing here decides it, and no numerics.

import os
import re
import sys
from pathlib import Path

from snakemake.exceptions import WorkflowError

from dice_core import DatasetError, planning, preflight, products, simulation, steps
from dice_core import resources as dice_resources
from dice_core.parallel import LANES
from dice_core import settings as dice_settings

BASE = Path(workflow.basedir)
SCRIPTS = BASE / "workflow" / "scripts"


def fail(message):
    """Stop the run with ``message``, one ``dice:`` line per line of it, and exit status 1: a problem of the
    configuration or the dataset, said before any job runs. A WorkflowError would wrap it in Snakemake's
    header and the file and line of this workflow, which are not the user's problem."""
    print("\n".join(f"dice: {line}" for line in str(message).splitlines()), file=sys.stderr)
    raise SystemExit(1)


def local_path(path):
    """A path relative to the working directory when it lies below it.

    Inputs must be spelt as the rules that make them spell their outputs, and
    those are relative; files outside the working directory stay absolute.
    """
    path = Path(path).resolve()
    cwd = Path.cwd().resolve()
    return str(path.relative_to(cwd)) if path.is_relative_to(cwd) else str(path)


try:
    SCHEMA = dice_settings.config_schema(BASE / "workflow" / "schemas" / "config.schema.yaml")
    _checked = dice_settings.checked(dict(config), SCHEMA, files=workflow.configfiles)
    config.clear()
    config.update(_checked)
    MANIFEST, SIMULATION = planning.load_dataset(
        str(config["dataset"]),
        presets=BASE / "config" / "presets",
        results=config["results"],
        raw=config.get("raw"),
        overrides=config.get("simulation"),
    )
except (dice_settings.SettingsError, planning.PlanningError) as exc:
    fail(exc)
OUT, SWEEP_ROOT = planning.run_roots(MANIFEST, config)
# A sweep point of the reduction alone reads its dataset's raw files where the main run simulates them
# (config raw), instead of simulating them again.
RAW = local_path(config["raw"]) if config.get("raw") else f"{OUT}/raw"
SIMULATE = SIMULATION is not None and not config.get("raw")
MANIFEST_FILE = local_path(MANIFEST.path)
# Products record their inputs relative to the dataset's folder (the manifest's) and to the results folder,
# tried in that order, so that they hold no absolute path of this machine (dice_core.io.write_product).
ROOTS = {"dataset": local_path(MANIFEST.path.parent), "results": OUT}
# A results folder that is a file would stop Snakemake itself while it plans the jobs, with its traceback.
for _root in (OUT, SWEEP_ROOT):
    if not preflight.nearest_existing(_root).is_dir():
        fail(
            f"cannot write in {preflight.nearest_existing(_root)} (a file, not a folder), where this run writes "
            f"{_root}; nothing was run"
        )
try:
    PLAN, DEFAULT_TARGETS = planning.plan_run(MANIFEST, config)  # every check of the plan made now
    SWEEPS = PLAN.sweeps
    PAPER_SWEEPS = {study: PLAN.paper_sweep(study) for study in config["paper"]}
except planning.PlanningError as exc:
    fail(exc)
REDUCTION_SWEEPS = [name for name, sweep in SWEEPS.items() if sweep.study == "reduction"]
STUDY_SWEEPS = [name for name in SWEEPS if name not in REDUCTION_SWEEPS]


wildcard_constraints:
    flat="|".join(map(re.escape, MANIFEST.flats)) or "(?!)",
    baseline="|".join(map(re.escape, MANIFEST.baselines)) or "(?!)",
    pair="|".join(map(re.escape, MANIFEST.pairs)) or "(?!)",
    mode="|".join(map(re.escape, dice_settings.choices()["modes"])),
    method="|".join(map(re.escape, dice_settings.choices()["methods"])),
    model="|".join(map(re.escape, dice_settings.choices()["superimpositions"][1:])),


# --------------------------------------------------------------------------- what a rule hands its step


def output_of(key, suffix="", **fixed):
    """The path pattern of catalogue product ``key`` (dice_core.products), as a rule's output or input; the
    ``fixed`` wildcards filled in."""
    pattern = products.pattern(key, dataset_root=OUT, sweeps_root=SWEEP_ROOT, suffix=suffix)
    for name, value in fixed.items():
        pattern = pattern.replace(f"{{{name}}}", str(value))
    return pattern


def figure_of(key, name="", *, category, caption):
    """A figure's two outputs: ``<name>png`` (in the report, with its caption) and ``<name>pdf``."""
    return {
        f"{name}png": report(output_of(key, ".png"), category=category, caption=f"../report/{caption}.rst"),
        f"{name}pdf": output_of(key, ".pdf"),
    }


def step_code(name):
    """Hash of the code a step runs (dice_core.steps.code_hash): its script, those of the steps it stands for
    (the split fit's fit_finish: a change to their scripts re-runs it), and the dice_core modules they import."""
    names = (name, *steps.step(name).stands_for)
    return steps.code_hash(SCRIPTS / f"{steps.step(n).script_name}.py" for n in names)


def step_params(name, **extra):
    """A rule's ``params:``, from step ``name``'s entry in dice_core.steps: ``settings``, exactly the
    configuration it reads (what its products record, and what re-runs it when changed), ``code``
    (:func:`step_code`), ``roots`` (what inputs are recorded relative to), and the rule's ``extra``."""
    keys = steps.settings_keys(name)
    if any("{" in key for key in keys):
        selected = lambda wildcards: dice_settings.select(config, keys, **dict(wildcards.items()))
    else:
        selected = dice_settings.select(config, keys)
    return {"settings": selected, "code": step_code(name), "roots": ROOTS, **extra}


# --------------------------------------------------------------------------- inputs


def acquisition_files(acquisition):
    return [local_path(f) for f in acquisition.files]


def flat_files(wildcards):
    return acquisition_files(MANIFEST.flats[wildcards.flat])


def baseline_files(wildcards):
    return acquisition_files(MANIFEST.baselines[wildcards.baseline])


def pair_baselines(wildcards):
    return list(MANIFEST.pairs[wildcards.pair])


def position_stacks(wildcards):
    """Every position's stars/<index>.nc, in acquisition order."""
    return [PLAN.path("stack", position=p.index) for p in MANIFEST.positions]


def fit_state(wildcards, npass):
    return PLAN.path("fit_state", baseline=wildcards.baseline, npass=npass)


def fit_part_of(wildcards, npass, part):
    return PLAN.path("fit_part", baseline=wildcards.baseline, npass=npass, part=part)


def sweeps_of(*studies):
    """The wildcard constraint of the sweeps of these studies (none: no job)."""
    return "|".join(re.escape(n) for n, sweep in SWEEPS.items() if sweep.study in studies) or "(?!)"


def reduction_point_tables(wildcards):
    """Each point's tables/accuracy.csv of a reduction sweep, in the config's order."""
    sweep = SWEEPS[wildcards.sweep]
    names = {
        folder: planning.point_dataset_name(
            config,
            REDUCTION_CONFIGS[planning.module_name(sweep.name, folder)],
            manifest_name=MANIFEST.name,
            presets=BASE / "config" / "presets",
        )
        for folder in sweep.folders
    }
    return [f"{SWEEP_ROOT}/{sweep.name}/{folder}/{name}/tables/accuracy.csv" for folder, name in names.items()]


# --------------------------------------------------------------------------- cluster resources
# Each rule's resources block (mem_mb, runtime) comes from step_resources: the measured cost of its step
# (dice_core.resources) applied to the job's share of the dataset. threads are 1 but for the jobs that read a
# baseline in parts (reading_threads).

SIM_FRAMES = (
    {rel: stop - start for rel, (_, _, start, stop) in simulation.file_jobs(SIMULATION).items()}
    if SIMULATION is not None
    else {}
)


# the run and its reduction sweep's points read the same files: one cache of their headers' frames
_FRAMES = dice_resources.FileFrames(MANIFEST, SIM_FRAMES, cache=vars(workflow).setdefault("_dice_file_frames", {}))


def file_frames(path):
    """Frames of a raw file: the simulation's plan where it simulates the file (it may not exist yet), else
    NAXIS3 of the file's header."""
    try:
        return _FRAMES(path)
    except DatasetError as exc:
        fail(exc)


# Every raw file's header read now, while the run's workflow is read (not by each job's Snakemake on a cluster
# node): a file that is not FITS is then said in one line, before the jobs are planned (the resources of a job
# read it, where an error is Snakemake's traceback).
if getattr(workflow, "is_main_process", True):
    for _file in MANIFEST.all_files():
        file_frames(_file)
# The jobs of the steps with many small inputs (config job_samples, docs/running.md "Jobs"): groups of star
# positions (their indices) for the stacks, groups of the simulation's files (numbered from 1 in the manifest's
# order) for the simulation; each group a rule, named by steps.group_rule.
PIXELS = MANIFEST.detector.shape[0] * MANIFEST.detector.shape[1]
POSITION_GROUPS = dice_resources.position_groups(
    MANIFEST.positions, file_frames, pixels=PIXELS, samples=config["job_samples"]
)
SIM_GROUPS = (
    dice_resources.simulation_groups(MANIFEST, file_frames, pixels=PIXELS, samples=config["job_samples"])
    if SIMULATE
    else []
)


def group_inputs(step, group):
    """The raw files of a group of step ``step``'s inputs (dice_core.resources.group_files), as the workflow
    spells them."""
    return [local_path(f) for f in dice_resources.group_files(MANIFEST, (step, group[0], group[-1]))]


# What the run skips and why, said once every start-up check has passed (a run refused at start says its one
# problem alone): by a run in its onstart, after the checks of the planned jobs (preflight.smk); by a dry run,
# which has no onstart, now. Snakemake tells the workflow nothing of a dry run while it reads it: the command
# line says it. One record for the run and the modules of its reduction sweep's points, which evaluate this
# file again with the same workflow object: a reason is said once, not once per point.
_SKIPPED = vars(workflow).setdefault("_dice_skipped", {})  # message: said yet
for _message in PLAN.skipped:
    _SKIPPED.setdefault(_message, False)
DRY_RUN = any(arg in ("--dry-run", "--dryrun") or re.fullmatch(r"-[A-Za-z]*n[A-Za-z]*", arg) for arg in sys.argv[1:])


def say_skipped():
    """Print each reason the run skips something that is not said yet, one ``dice:`` line each."""
    for message, said in _SKIPPED.items():
        if not said:
            _SKIPPED[message] = True
            print(f"dice: {message}", file=sys.stderr)


if DRY_RUN:
    say_skipped()


def run_cores():
    """The cores this run's jobs share (--cores), where they run on this machine; None where each job has a slot
    of its own: under a cluster's executor, in the process that submits the jobs (whatever --cores says) and
    in each job's own Snakemake on its node, which reads this file again with other cores (the submitter's
    --cores, or its slot's CPUs), so that a job's threads there are those it was submitted with. None too
    where Snakemake has no total."""
    if not (workflow.is_main_process and workflow.local_exec):
        return None
    try:
        return workflow.cores
    except WorkflowError:
        return None


RUN_CORES = run_cores()


def reading_threads(parts):
    """A rule's threads: for a job that reads baseline ``wildcards.baseline`` in ``parts`` parts, its worker
    processes, one per part for a large baseline, one for a small, and no more than the run's cores shared
    among its baselines (dice_core.resources.reading_workers)."""

    def threads(wildcards):
        files = MANIFEST.baselines[wildcards.baseline].files
        return dice_resources.reading_workers(
            files, file_frames, pixels=PIXELS, parts=parts, cores=RUN_CORES, baselines=len(MANIFEST.baselines)
        )

    return threads


def part_files(wildcards):
    """The files of part ``wildcards.part`` of a split fit of ``wildcards.baseline`` (its group of whole files)."""
    files = acquisition_files(MANIFEST.baselines[wildcards.baseline])
    return dice_resources.part_files(files, file_frames, parts=config["metrology"]["parts"], part=int(wildcards.part))


def step_resources(step, **fixed):
    """A rule's resources block, ``resources: **step_resources("<rule>")``: mem_mb (MB) and runtime (minutes)
    of each job from its step's measured cost and the job's data, times the attempt on a retry. ``fixed``: what
    the job's wildcards would say of a rule without them (a group's ``positions`` or ``files``)."""

    # threads: the job's, as Snakemake gives them (--set-threads, --max-threads and --cores applied): a
    # baseline's fit and Allan jobs ask for the memory of the workers they run
    def needs(wildcards, input, threads, attempt):
        data = dice_resources.job_data(
            step,
            {**dict(wildcards.items()), **fixed},
            manifest=MANIFEST,
            frames_of=file_frames,
            parts=config["metrology"]["parts"],
            inputs=dict(input.items()),
            workers=threads,
        )
        return dice_resources.job_resources(
            step,
            pixels=PIXELS,
            **data,
            chunk_frames=config["chunk_frames"],
            attempt=attempt,
        )

    # with input: Snakemake evaluates a job's resources again when it is about to run, its inputs written (the
    # Allan job's batches from its metrology product)
    return {
        "mem_mb": lambda wildcards, input, threads, attempt: needs(wildcards, input, threads, attempt)["mem_mb"],
        "runtime": lambda wildcards, input, threads, attempt: needs(wildcards, input, threads, attempt)["runtime"],
    }
