# Sweeps (config sweeps) and the `paper` target: the paper's simulation studies one job per
# sweep point (dice_core.planning.plan_sweep), and every regenerated number beside the paper's.
#
#   snakemake --cores 2 paper        # the reduction of the dataset, the studies, the comparison


if SWEEPS:

    wildcard_constraints:
        sweep="|".join(map(re.escape, SWEEPS)),


rule sweep_point:
    output:
        point=output_of("sweep_point"),
    log:
        f"{SWEEP_ROOT}/{{sweep}}/{{point}}/point.log",
    benchmark:
        f"{SWEEP_ROOT}/{{sweep}}/{{point}}/benchmark.tsv"
    wildcard_constraints:  # only the configured points: another folder is no job, not a cryptic error
        sweep="|".join(map(re.escape, STUDY_SWEEPS)) or "(?!)",
        point="|".join(sorted({re.escape(folder) for name in STUDY_SWEEPS for folder in SWEEPS[name].folders}))
        or "(?!)",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("sweep_point"),
    params:
        **step_params("sweep_point", parameters=lambda w: PLAN.point_parameters(w.sweep, w.point)),
    script:
        "../scripts/sweep_point.py"


# Each point of a reduction sweep is the whole workflow again (a Snakemake module) with the point's config,
# its products under results/sweeps/<sweep>/<point>/, without the steps of the run as a whole.
REDUCTION_CONFIGS = {}
try:
    for _name in REDUCTION_SWEEPS:
        for _index, _folder in enumerate(SWEEPS[_name].folders):
            REDUCTION_CONFIGS[planning.module_name(_name, _folder)] = planning.reduction_point_config(
                config, SWEEPS[_name], index=_index, simulated=SIMULATION is not None, raw=RAW, sweeps_root=SWEEP_ROOT
            )
except planning.PlanningError as exc:
    fail(exc)
RUN_LEVEL_RULES = ["all", "paper", *(name for name, step in steps.STEPS.items() if step.whole_run)]
for _point_module, _point_config in REDUCTION_CONFIGS.items():
    # what `module <name>: snakefile: ...; config: ...` and `use rule * from <name> exclude ... as <name>_*`
    # compile to: the statements cannot be written in a loop, their calls can
    workflow.module(name=_point_module, snakefile=workflow.main_snakefile, config=_point_config)
    workflow.userule(
        rules=["*"], from_module=_point_module, exclude_rules=RUN_LEVEL_RULES, name_modifier=f"{_point_module}_*"
    )(lambda: None)


rule reduction_sweep_summary:
    input:
        tables=reduction_point_tables,
    output:
        **figure_of("sweep_accuracy_figure", category="Sweeps", caption="reduction_sweep"),
        csv=output_of("sweep_summary"),
    log:
        f"{SWEEP_ROOT}/{{sweep}}/summary.log",
    wildcard_constraints:
        sweep=sweeps_of("reduction"),
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("reduction_sweep_summary"),
    params:
        **step_params(
            "reduction_sweep_summary",
            points=lambda w: [
                {k: planning.folder_value(v) for k, v in point.items()} for point in SWEEPS[w.sweep].points
            ],
        ),
    script:
        "../scripts/reduction_sweep_summary.py"


rule sweep_summary:
    input:
        points=lambda w: PLAN.sweep_points(w.sweep),
    output:
        csv=output_of("sweep_summary"),
    log:
        f"{SWEEP_ROOT}/{{sweep}}/summary.log",
    wildcard_constraints:
        sweep="|".join(map(re.escape, STUDY_SWEEPS)) or "(?!)",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("sweep_summary"),
    params:
        **step_params("sweep_summary"),
    script:
        "../scripts/sweep_summary.py"


rule plot_star_accuracy:
    input:
        points=lambda w: PLAN.sweep_points(w.sweep),
    output:
        **figure_of("sweep_accuracy_figure", category="Sweeps", caption="star_accuracy"),
    log:
        f"{SWEEP_ROOT}/{{sweep}}/accuracy.log",
    wildcard_constraints:
        sweep=sweeps_of("star_accuracy"),
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_star_accuracy"),
    params:
        **step_params("plot_star_accuracy"),
    script:
        "../scripts/plot_star_accuracy.py"


rule plot_tip_tilt:
    input:
        points=lambda w: PLAN.sweep_points(w.sweep),
    output:
        **figure_of("tip_tilt_figure", category="Sweeps", caption="tip_tilt"),
    log:
        f"{SWEEP_ROOT}/{{sweep}}/tip_tilt.log",
    wildcard_constraints:
        sweep=sweeps_of("tip_tilt"),
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_tip_tilt"),
    params:
        **step_params("plot_tip_tilt"),
    script:
        "../scripts/plot_tip_tilt.py"


rule plot_chromatic_study:
    input:
        points=lambda w: PLAN.sweep_points(w.sweep),
    output:
        **figure_of("chromatic_study_figure", category="Sweeps", caption="chromatic_study"),
    log:
        f"{SWEEP_ROOT}/{{sweep}}/chromatic.log",
    wildcard_constraints:
        sweep=sweeps_of("chromatic"),
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_chromatic_study"),
    params:
        **step_params("plot_chromatic_study"),
    script:
        "../scripts/plot_chromatic_study.py"


rule plot_offset_bias:
    input:
        points=PLAN.sweep_points(PAPER_SWEEPS["offset_bias"]),
    output:
        **figure_of("figure_offset_bias", category="Numerical simulations", caption="offset_bias"),
    log:
        f"{OUT}/logs/plot_offset_bias.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_offset_bias"),
    params:
        **step_params("plot_offset_bias"),
    script:
        "../scripts/plot_offset_bias.py"


rule plot_stray_light_study:
    input:
        points=PLAN.sweep_points(PAPER_SWEEPS["stray_light"]),
    output:
        **figure_of("figure_stray_light_study", category="Numerical simulations", caption="stray_light_study"),
    log:
        f"{OUT}/logs/plot_stray_light_study.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_stray_light_study"),
    params:
        **step_params("plot_stray_light_study"),
    script:
        "../scripts/plot_stray_light_study.py"


rule error_propagation_table:
    input:
        points=PLAN.sweep_points(PAPER_SWEEPS["error_propagation"]),
    output:
        csv=output_of("error_propagation"),
    log:
        f"{OUT}/logs/error_propagation_table.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("error_propagation_table"),
    params:
        **step_params("error_propagation_table"),
    script:
        "../scripts/error_propagation_table.py"


rule plot_error_propagation:  # apart from the table: a plot edit re-runs the plot alone
    input:
        points=PLAN.sweep_points(PAPER_SWEEPS["error_propagation"]),
    output:
        **figure_of("figure_error_propagation", category="Numerical simulations", caption="error_propagation"),
    log:
        f"{OUT}/logs/plot_error_propagation.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_error_propagation"),
    params:
        **step_params("plot_error_propagation"),
    script:
        "../scripts/plot_error_propagation.py"


rule procrustes_deflation:  # a Monte Carlo of its own: the comparison's figure never re-runs it
    output:
        csv=output_of("procrustes_deflation"),
    log:
        f"{OUT}/logs/procrustes_deflation.log",
    benchmark:
        f"{OUT}/benchmarks/procrustes_deflation.tsv"
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("procrustes_deflation"),
    params:
        **step_params("procrustes_deflation"),
    script:
        "../scripts/procrustes_deflation.py"


rule paper_comparison:
    input:
        **PLAN.comparison_inputs(),
    output:
        **figure_of("figure_paper_comparison", category="Paper comparison", caption="paper_comparison"),
        csv=output_of("paper_comparison"),
    log:
        f"{OUT}/logs/paper_comparison.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("paper_comparison"),
    params:
        **step_params("paper_comparison", dataset=MANIFEST.name),
    script:
        "../scripts/paper_comparison.py"


PAPER_PAGES = planning.paper_pdf_pages(PLAN, BASE / "workflow" / "report")


rule paper_pdf:
    input:
        figures=[png for png, _ in PAPER_PAGES],
        captions=[caption for _, caption in PAPER_PAGES],  # an edited caption rebuilds it
        comparison=output_of("paper_comparison"),
    output:
        pdf=output_of("paper_report"),
    log:
        f"{OUT}/logs/paper_pdf.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("paper_pdf"),
    params:
        **step_params("paper_pdf", dataset=MANIFEST.name),
    script:
        "../scripts/paper_pdf.py"


rule paper:
    input:
        rules.paper_pdf.output,
        DEFAULT_TARGETS,
        rules.plot_offset_bias.output,
        rules.plot_stray_light_study.output,
        rules.error_propagation_table.output,
        rules.plot_error_propagation.output,
        rules.paper_comparison.output,
        [PLAN.path("sweep_summary", sweep=name) for name in PAPER_SWEEPS.values()],
        PLAN.figure("chromatic_study_figure", sweep=PAPER_SWEEPS["chromatic"]),
