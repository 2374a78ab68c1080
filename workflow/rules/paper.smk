# Sweeps (config sweeps) and the `paper` target: the paper's simulation studies one job per
# sweep point (Snakemake's Paramspace), and every regenerated number beside the paper's.
#
#   snakemake --cores 2 paper        # the reduction of the dataset, the studies, the comparison


import itertools

from pandas import DataFrame
from snakemake.utils import Paramspace

SWEEP_ROOT = f"{config['results']}/sweeps"


def sweep_space(name, spec):
    """(Paramspace with one wildcard 'point', column -> parameter key) of a configured sweep."""
    if "points" in spec:
        points = [dict(p) for p in spec["points"]]
    elif "grid" in spec:  # every combination, the first parameter varying slowest
        keys = list(spec["grid"])
        points = [dict(zip(keys, combination)) for combination in itertools.product(*spec["grid"].values())]
    else:
        points = [{spec["parameter"]: value} for value in spec["values"]]
    keys = sorted({key for p in points for key in p})
    if any(set(p) != set(keys) for p in points):
        raise WorkflowError(f"config sweeps.{name}.points: every point must set the same parameters {keys}")
    columns = {key.rsplit(".", 1)[-1]: key for key in keys}  # folder names: the key's last part
    if len(columns) != len(keys):
        raise WorkflowError(f"config sweeps.{name}: parameters {keys} share a last name; folders would clash")
    frame = DataFrame([{column: p[key] for column, key in columns.items()} for p in points])
    if frame.duplicated().any():
        raise WorkflowError(f"config sweeps.{name}: a point is listed twice")
    return Paramspace(frame, single_wildcard="point"), columns


SWEEPS = {name: (spec, *sweep_space(name, spec)) for name, spec in config.get("sweeps", {}).items()}


def sweep_points(name):
    """The point products of a configured sweep, in the config's order."""
    if name not in SWEEPS:
        raise WorkflowError(f"no sweep named {name!r} in config sweeps (sweeps: {', '.join(SWEEPS) or 'none'})")
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
        raise WorkflowError(f"config paper.{study}: {name!r} is not a sweep of study {study} in config sweeps")
    return name


if SWEEPS:

    wildcard_constraints:
        sweep="|".join(map(re.escape, SWEEPS)),


rule sweep_point:
    output:
        point=f"{SWEEP_ROOT}/{{sweep}}/{{point}}/point.nc",
    params:
        study=lambda w: SWEEPS[w.sweep][0]["study"],
        parameters=point_parameters,
        bench=lambda w: SWEEPS[w.sweep][0].get("bench", {}),
        options=lambda w: SWEEPS[w.sweep][0].get("options", {}),
        code=code_version("studies"),
    log:
        f"{SWEEP_ROOT}/{{sweep}}/{{point}}/point.log",
    benchmark:
        f"{SWEEP_ROOT}/{{sweep}}/{{point}}/benchmark.tsv"
    conda:
        "../envs/dice.yaml"
    script:
        "../scripts/sweep_point.py"


rule sweep_summary:
    input:
        points=lambda w: sweep_points(w.sweep),
    output:
        csv=f"{SWEEP_ROOT}/{{sweep}}/summary.csv",
    params:
        code=code_version("io"),
    log:
        f"{SWEEP_ROOT}/{{sweep}}/summary.log",
    conda:
        "../envs/dice.yaml"
    script:
        "../scripts/sweep_summary.py"


rule plot_offset_bias:
    input:
        points=lambda w: sweep_points(paper_sweep("offset_bias")),
    output:
        png=report(f"{OUT}/figures/offset_bias.png", category="Numerical simulations",
                   caption="../report/offset_bias.rst"),
        pdf=f"{OUT}/figures/offset_bias.pdf",
    params:
        code=code_version("plotting", "io"),
    log:
        f"{OUT}/logs/plot_offset_bias.log",
    conda:
        "../envs/dice.yaml"
    script:
        "../scripts/plot_offset_bias.py"


rule error_propagation_table:
    input:
        points=lambda w: sweep_points(paper_sweep("error_propagation")),
    output:
        csv=f"{OUT}/tables/error_propagation.csv",
        png=report(f"{OUT}/figures/error_propagation.png", category="Numerical simulations",
                   caption="../report/error_propagation.rst"),
        pdf=f"{OUT}/figures/error_propagation.pdf",
    params:
        code=code_version("studies", "error_budget", "io"),
    log:
        f"{OUT}/logs/error_propagation_table.log",
    conda:
        "../envs/dice.yaml"
    script:
        "../scripts/error_propagation_table.py"


def comparison_inputs(wildcards=None):
    """What the comparison reads: the studies, and this dataset's accuracy table and Allan products."""
    inputs = {"offset_bias": sweep_points(paper_sweep("offset_bias")),
              "error_propagation": f"{OUT}/tables/error_propagation.csv"}
    if astrometry_targets():
        inputs["accuracy"] = f"{OUT}/tables/accuracy.csv"
    if metrology_unavailable() is None:
        inputs["allan"] = [f"{OUT}/allan/{baseline}.nc" for baseline in MANIFEST.baselines]
    return inputs


rule paper_comparison:
    input:
        unpack(comparison_inputs),
    output:
        csv=f"{OUT}/tables/paper_comparison.csv",
        png=report(f"{OUT}/figures/paper_comparison.png", category="Paper comparison",
                   caption="../report/paper_comparison.rst"),
        pdf=f"{OUT}/figures/paper_comparison.pdf",
    params:
        code=code_version("reproduction", "plotting", "io"),
        dataset=MANIFEST.name,
        positions=config["astrometry"]["positions"],
        trials=config["astrometry"]["trials"],
    log:
        f"{OUT}/logs/paper_comparison.log",
    conda:
        "../envs/dice.yaml"
    script:
        "../scripts/paper_comparison.py"


rule paper:
    input:
        calibration_targets(),
        metrology_targets(),
        centroid_targets(),
        astrometry_targets(),
        rules.plot_offset_bias.output,
        rules.error_propagation_table.output,
        rules.paper_comparison.output,
        [f"{SWEEP_ROOT}/{name}/summary.csv" for name in SWEEPS],
