"""The table of the workflow's steps: what each reads of the configuration and what it writes.

One entry per step, said once; the rest is derived from it. A step is a
workflow rule of the same name that runs ``workflow/scripts/<script>.py``. Its
``settings`` (dotted configuration keys, possibly with ``{wildcard}`` fields)
are all it reads of the configuration: the rule hands the script exactly those
(:func:`dice_core.settings.select`), Snakemake re-runs the step when one of them
changes, and each product the step writes records them as its
``configuration``. The library modules it runs are those its script imports,
followed through ``dice_core`` (the code hash the workflow re-runs it by); its
products are entries of :data:`dice_core.products.CATALOGUE`.

``stands_for`` names the steps a step answers for: ``fit_finish`` stands for
the split fit's passes, whose states are temporary, so that a change to their
settings or scripts re-runs it (and, through its missing inputs, them).
``whole_run`` marks the steps of the run as a whole (the sweeps, the paper's
studies and report), which a reduction sweep's point, the whole workflow again
for one dataset, leaves out.

The steps of many small inputs (``stack_position``: the star positions;
``simulate_file``: the simulated files) run one job per group of consecutive
inputs (config ``job_samples``), each group a rule of its own, named by
:func:`group_rule` (``stack_position_1_to_90``); :func:`step_of_rule` gives any
rule's step.

Keys no step declares only plan what is made, not how: the dataset and where
results go (``dataset``, ``results``, ``raw``, ``simulation``: another results
folder), the sweeps' points (``sweeps.<name>.values``...: which points exist),
and ``metrology.split`` (how the fit runs; its product is the single job's bit
for bit). :data:`PLANNING_KEYS` lists them, with why.
"""

from __future__ import annotations

import ast
import functools
import hashlib
import re
from dataclasses import dataclass
from pathlib import Path

__all__ = ["Step", "STEPS", "PLANNING_KEYS", "DESCRIPTIVE", "step", "settings_keys", "GROUPED", "group_rule",
           "rule_group", "step_of_rule", "code_hash", "code_modules", "dice_core_imports"]


@dataclass(frozen=True)
class Step:
    """One step of the workflow (the module's docstring gives the conventions)."""

    name: str
    settings: tuple[str, ...] = ()
    script: str = ""
    stands_for: tuple[str, ...] = ()
    whole_run: bool = False  # a step of the run as a whole (sweeps, the paper), not of one dataset

    @property
    def script_name(self) -> str:
        """The script it runs, ``workflow/scripts/<script_name>.py``."""
        return self.script or self.name

    @property
    def writes(self) -> tuple[str, ...]:
        """The catalogue's products it writes (:data:`dice_core.products.CATALOGUE` names each one's steps)."""
        from dice_core.products import CATALOGUE

        return tuple(key for key, p in CATALOGUE.items() if self.name in (p.step, *p.extra))


_STREAM = ("chunk_frames",)  # a step that streams cubes: the chunks' size sets the sums' order, hence the bits
_FIT = ("metrology.tolerance", "metrology.max_passes", "metrology.smooth_degree", "metrology.use_flat")
_ASTROMETRY = ("astrometry.positions", "astrometry.groups", "astrometry.trials", "astrometry.superimposition",
               "astrometry.pose.distance", "astrometry.pose.off_axis_deg", "astrometry.pose.centre")
_SWEEP = ("sweeps.{sweep}.study", "sweeps.{sweep}.bench", "sweeps.{sweep}.options")

_STEPS = [
    # the simulated testbed: its settings are the preset (config dataset) with config simulation's overrides,
    # which the rules hand over whole as the simulation's configuration
    Step("simulate_truth"),
    Step("simulate_file"),
    Step("simulate_manifest"),
    # dark and flat field
    Step("measure_dark", _STREAM),
    Step("measure_prnu", (*_STREAM, "prnu.gradient_degree")),
    Step("select_reference_prnu"),
    Step("compare_prnu"),
    Step("find_bad_pixels"),
    # metrology
    Step("fit_fringes", (*_STREAM, *_FIT, "metrology.parts", "metrology.tip_sigma")),
    Step("fit_start", (*_STREAM, *_FIT, "metrology.parts")),
    Step("fit_part", (*_STREAM, *_FIT, "metrology.parts")),
    Step("fit_reduce", _FIT),
    Step("fit_finish", (*_STREAM, *_FIT, "metrology.parts", "metrology.tip_sigma"),
         stands_for=("fit_start", "fit_part", "fit_reduce")),
    Step("prf_widths", ("prf.order", "prf.half_width", "prf.sigma", "metrology.smooth_degree")),
    Step("find_stray_light"),
    Step("deproject_offsets"),  # metrology.stray_light: remove gives it the stray-light products as inputs
    Step("chromatic_calibration", ("prf.order", "prf.half_width", "prf.sigma", "metrology.smooth_degree")),
    Step("compare_pairs", ("metrology.stray_light",)),
    Step("allan_deviation", _STREAM),
    # pseudo stars and astrometry
    Step("stack_position", (*_STREAM, "centroids.batches")),
    Step("measure_centroids", ("centroids.method", "centroids.half_size", "centroids.pair", "centroids.spectrum")),
    Step("measure_centroids_by_method", ("centroids.half_size", "centroids.pair", "centroids.spectrum"),
         script="measure_centroids"),
    Step("accuracy_table", ("centroids.modes", "centroids.method", "centroids.methods", *_ASTROMETRY)),
    # figures
    Step("plot_dark"),
    Step("plot_prnu"),
    Step("plot_prnu_difference"),
    Step("plot_metrology"),
    Step("plot_allan"),
    Step("plot_offsets"),
    Step("plot_offsets_difference"),
    Step("plot_stray_light"),
    Step("plot_prf"),
    Step("plot_chromatic"),
    Step("plot_centroids", ("astrometry.positions",)),
    Step("plot_procrustes_residuals"),
    Step("plot_superimposition_residuals"),
    # sweeps and the paper
    Step("sweep_point", _SWEEP, whole_run=True),
    Step("sweep_summary", whole_run=True),
    Step("reduction_sweep_summary", whole_run=True),
    Step("plot_star_accuracy", whole_run=True),
    Step("plot_tip_tilt", whole_run=True),
    Step("plot_chromatic_study", whole_run=True),
    Step("plot_offset_bias", ("paper.offset_bias",), whole_run=True),
    Step("error_propagation_table", ("paper.error_propagation",), whole_run=True),
    Step("plot_error_propagation", ("paper.error_propagation",), whole_run=True),
    Step("plot_stray_light_study", ("paper.stray_light",), whole_run=True),
    Step("procrustes_deflation", ("astrometry.trials",), whole_run=True),
    Step("paper_comparison", ("paper.offset_bias", "paper.error_propagation", "paper.stray_light",
                              "paper.chromatic", "astrometry.positions", "centroids.method",
                              "metrology.stray_light"), whole_run=True),
    Step("paper_pdf", whole_run=True),
]

#: Every step by name.
STEPS: dict[str, Step] = {s.name: s for s in _STEPS}

#: The configuration keys that no step reads, with why: they choose what is made or where, not how.
PLANNING_KEYS = {
    "dataset": "the dataset: another results folder",
    "results": "where results go: another results folder",
    "raw": "where a sweep point's raw files are: set by the workflow itself",
    "simulation": "the preset's overrides: another dataset, named by their hash, in its own folder",
    "sweeps": "which sweeps and points exist; a point's own settings are its step's (sweeps.<name>.study, "
              "bench, options)",
    "job_samples": "how the simulated files and the star positions are cut into jobs, not what the jobs make "
                   "(docs/running.md, \"Jobs\")",
    "metrology.split": "how the fit runs, as one job or as many: its product is the single job's bit for bit, but "
                       "another rule makes it, so switching re-runs the fits, and what follows, once",
}


def step(name: str) -> Step:
    """The table's entry ``name``; a KeyError names the known steps."""
    try:
        return STEPS[name]
    except KeyError:
        raise KeyError(f"no step {name!r} in the step table (steps: {', '.join(STEPS)})") from None


#: The steps with one job per group of consecutive inputs (config ``job_samples``): the simulation's files, the
#: star positions' stacks.
GROUPED = ("simulate_file", "stack_position")


def group_rule(name: str, numbers) -> str:
    """The rule of step ``name`` (of :data:`GROUPED`) for a group of its inputs, numbered in order (the star
    positions' indices; the simulated files' places in the manifest, from 1): ``<name>_<first>`` for one,
    ``<name>_<first>_to_<last>`` for several."""
    if name not in GROUPED:
        raise KeyError(f"step {name!r} has no jobs by groups of inputs ({', '.join(GROUPED)})")
    first, last = numbers[0], numbers[-1]
    return f"{name}_{first}" if len(numbers) == 1 else f"{name}_{first}_to_{last}"


def rule_group(rule: str) -> tuple[str, int, int] | None:
    """(step, first, last) of a group's rule (:func:`group_rule`), None for any other rule."""
    match = re.fullmatch(r"(\w+?)_(\d+)(?:_to_(\d+))?", rule)
    if match is None or match.group(1) not in GROUPED:
        return None
    first, last = int(match.group(2)), int(match.group(3) or match.group(2))
    return (match.group(1), first, last) if first < last or match.group(3) is None else None


def step_of_rule(rule: str) -> str:
    """The step a workflow rule runs: the rule's own name, or the step of a group's rule (:func:`group_rule`);
    a KeyError for a name that is neither."""
    if rule in STEPS:
        return rule
    if (group := rule_group(rule)) is not None:
        return group[0]
    raise KeyError(f"no step runs rule {rule!r} (steps: {', '.join(STEPS)})")


def settings_keys(name: str) -> tuple[str, ...]:
    """The settings a step reads, with those of the steps it stands for, once each in order."""
    entry = step(name)
    keys = [*entry.settings, *(k for other in entry.stands_for for k in step(other).settings)]
    return tuple(dict.fromkeys(keys))




#: dice_core modules that describe the workflow rather than compute a product: what is made, where, with which
#: settings, and how it is checked. A step's code hash does not follow them, so that declaring a new product or
#: setting re-runs nothing it does not change (a product's path or settings changing re-run it by themselves).
DESCRIPTIVE = frozenset({"products", "products_page", "steps", "settings", "planning", "preflight", "resources"})


@functools.lru_cache(maxsize=None)
def _imports(path: str, mtime_ns: int) -> frozenset:
    names = set()
    for node in ast.walk(ast.parse(Path(path).read_text())):
        if isinstance(node, ast.ImportFrom) and node.module == "dice_core":
            names |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith("dice_core."):
            names.add(node.module.split(".")[1])
        elif isinstance(node, ast.Import):
            names |= {alias.name.split(".")[1] for alias in node.names if alias.name.startswith("dice_core.")}
    return frozenset(names)


def dice_core_imports(path) -> set[str]:
    """Names a source file imports from dice_core, at its top or inside functions: its modules, and other
    names (classes, functions), which :func:`code_modules` tells apart by looking for their files. Read once
    per version of the file (the workflow asks for every step's rule)."""
    path = Path(path)
    return set(_imports(str(path), path.stat().st_mtime_ns))


def code_modules(scripts) -> set[str]:
    """The dice_core modules ``scripts`` run: those they import, followed through the modules' own imports,
    and the package's ``__init__``; not the modules of :data:`DESCRIPTIVE`."""
    package = Path(__file__).parent
    todo = ["__init__", *(name for script in scripts for name in sorted(dice_core_imports(script)))]
    closure = set()
    while todo:
        name = todo.pop()
        if name in closure or name in DESCRIPTIVE or not (package / f"{name}.py").is_file():
            continue  # a described module, or a class or function, not a module
        closure.add(name)
        todo += sorted(dice_core_imports(package / f"{name}.py"))
    return closure


def code_hash(scripts) -> str:
    """Hash (16 hex digits) of the code that ``scripts`` run: their own bytes and those of
    :func:`code_modules`. A step's rule passes it as a parameter (Snakemake re-runs a job whose parameters
    changed), so that an edit to a module re-runs the steps that use it, directly or through another module,
    and only those."""
    package = Path(__file__).parent
    scripts = [Path(script) for script in scripts]
    digest = hashlib.sha256()
    for path in [*scripts, *(package / f"{name}.py" for name in sorted(code_modules(scripts)))]:
        digest.update(path.read_bytes())
    return digest.hexdigest()[:16]
