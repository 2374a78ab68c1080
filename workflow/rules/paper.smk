# Sweeps (config sweeps) and the `paper` target: the paper's simulation studies one job per
# sweep point (Snakemake's Paramspace), and every regenerated number beside the paper's.
#
#   snakemake --cores 2 paper        # the reduction of the dataset, the studies, the comparison


if SWEEPS:

    wildcard_constraints:
        sweep="|".join(map(re.escape, SWEEPS)),


rule sweep_point:
    output:
        point=f"{SWEEP_ROOT}/{{sweep}}/{{point}}/point.nc",
    log:
        f"{SWEEP_ROOT}/{{sweep}}/{{point}}/point.log",
    benchmark:
        f"{SWEEP_ROOT}/{{sweep}}/{{point}}/benchmark.tsv"
    wildcard_constraints:  # only the configured points: another folder is no job, not a cryptic error
        sweep="|".join(map(re.escape, STUDY_SWEEPS)) or "(?!)",
        point="|".join(
            sorted({re.escape(pattern) for name in STUDY_SWEEPS for pattern in SWEEPS[name][1].instance_patterns})
        )
        or "(?!)",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("sweep_point"),
    params:
        study=lambda w: SWEEPS[w.sweep][0]["study"],
        parameters=point_parameters,
        bench=lambda w: SWEEPS[w.sweep][0].get("bench", {}),
        options=lambda w: SWEEPS[w.sweep][0].get("options", {}),
        code=code_version("studies"),
    script:
        "../scripts/sweep_point.py"


# Rules of the run as a whole, not of one point: a point's module leaves them out.
RUN_LEVEL_RULES = (
    "all",
    "paper",
    "paper_pdf",
    "paper_comparison",
    "plot_offset_bias",
    "error_propagation_table",
    "plot_error_propagation",
    "procrustes_deflation",
    "sweep_point",
    "sweep_summary",
    "plot_star_accuracy",
    "reduction_sweep_summary",
)
REDUCTION_CONFIGS = {
    module_name(name, folder): reduction_point_config(name, point, folder)
    for name in REDUCTION_SWEEPS
    for point, folder in sweep_instances(name)
}

if REDUCTION_CONFIGS:
    # Each point of a reduction sweep is the whole workflow again (a Snakemake module) with the point's
    # config, its products under results/sweeps/<sweep>/<point>/. Modules cannot be declared in a loop,
    # so their declarations are written out (the configs stay here, named), then included; the file is
    # named by its content, so that runs with other sweeps in the same folder never share one.
    declarations = []
    for point_module in REDUCTION_CONFIGS:
        declarations += [
            f"module {point_module}:",
            f"    snakefile: {workflow.main_snakefile!r}",
            f"    config: REDUCTION_CONFIGS[{point_module!r}]",
            "",
            f"use rule * from {point_module} exclude {', '.join(RUN_LEVEL_RULES)} as {point_module}_*",
            "",
            "",
        ]
    text = "# Written by workflow/rules/paper.smk from config sweeps; do not edit.\n\n" + "\n".join(declarations)
    generated = Path(".snakemake/dice") / f"reduction_sweeps_{hashlib.sha256(text.encode()).hexdigest()[:12]}.smk"
    if not generated.is_file():
        write_text(generated, text)  # atomically, readable as the umask allows

    include: str(generated.resolve())


rule reduction_sweep_summary:
    input:
        tables=reduction_point_tables,
    output:
        csv=f"{SWEEP_ROOT}/{{sweep}}/summary.csv",
        png=f"{SWEEP_ROOT}/{{sweep}}/accuracy.png",
        pdf=f"{SWEEP_ROOT}/{{sweep}}/accuracy.pdf",
    log:
        f"{SWEEP_ROOT}/{{sweep}}/summary.log",
    wildcard_constraints:
        sweep="|".join(map(re.escape, REDUCTION_SWEEPS)) or "(?!)",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("reduction_sweep_summary"),
    params:
        points=lambda w: [{k: folder_value(v) for k, v in point.items()} for point, _ in sweep_instances(w.sweep)],
        code=code_version("plotting", "io"),
    script:
        "../scripts/reduction_sweep_summary.py"


rule sweep_summary:
    input:
        points=lambda w: sweep_points(w.sweep),
    output:
        csv=f"{SWEEP_ROOT}/{{sweep}}/summary.csv",
    log:
        f"{SWEEP_ROOT}/{{sweep}}/summary.log",
    wildcard_constraints:
        sweep="|".join(map(re.escape, STUDY_SWEEPS)) or "(?!)",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("sweep_summary"),
    params:
        code=code_version("io"),
    script:
        "../scripts/sweep_summary.py"


rule plot_star_accuracy:
    input:
        points=lambda w: sweep_points(w.sweep),
    output:
        png=f"{SWEEP_ROOT}/{{sweep}}/accuracy.png",
        pdf=f"{SWEEP_ROOT}/{{sweep}}/accuracy.pdf",
    log:
        f"{SWEEP_ROOT}/{{sweep}}/accuracy.log",
    wildcard_constraints:
        sweep="|".join(re.escape(n) for n, (spec, *_) in SWEEPS.items() if spec["study"] == "star_accuracy") or "(?!)",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_star_accuracy"),
    params:
        code=code_version("plotting", "io"),
    script:
        "../scripts/plot_star_accuracy.py"


rule plot_tip_tilt:
    input:
        points=lambda w: sweep_points(w.sweep),
    output:
        png=f"{SWEEP_ROOT}/{{sweep}}/tip_tilt.png",
        pdf=f"{SWEEP_ROOT}/{{sweep}}/tip_tilt.pdf",
    log:
        f"{SWEEP_ROOT}/{{sweep}}/tip_tilt.log",
    wildcard_constraints:
        sweep="|".join(re.escape(n) for n, (spec, *_) in SWEEPS.items() if spec["study"] == "tip_tilt") or "(?!)",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_tip_tilt"),
    params:
        code=code_version("plotting", "io"),
    script:
        "../scripts/plot_tip_tilt.py"


rule plot_offset_bias:
    input:
        points=lambda w: sweep_points(paper_sweep("offset_bias")),
    output:
        png=report(
            f"{OUT}/figures/offset_bias.png", category="Numerical simulations", caption="../report/offset_bias.rst"
        ),
        pdf=f"{OUT}/figures/offset_bias.pdf",
    log:
        f"{OUT}/logs/plot_offset_bias.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_offset_bias"),
    params:
        code=code_version("plotting", "io"),
    script:
        "../scripts/plot_offset_bias.py"


rule error_propagation_table:
    input:
        points=lambda w: sweep_points(paper_sweep("error_propagation")),
    output:
        csv=f"{OUT}/tables/error_propagation.csv",
    log:
        f"{OUT}/logs/error_propagation_table.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("error_propagation_table"),
    params:
        code=code_version("studies", "error_budget", "io"),
    script:
        "../scripts/error_propagation_table.py"


rule plot_error_propagation:  # apart from the table: a plot edit re-runs the plot alone
    input:
        points=lambda w: sweep_points(paper_sweep("error_propagation")),
    output:
        png=report(
            f"{OUT}/figures/error_propagation.png",
            category="Numerical simulations",
            caption="../report/error_propagation.rst",
        ),
        pdf=f"{OUT}/figures/error_propagation.pdf",
    log:
        f"{OUT}/logs/plot_error_propagation.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_error_propagation"),
    params:
        code=code_version("studies", "plotting", "io"),
    script:
        "../scripts/plot_error_propagation.py"


rule procrustes_deflation:  # a Monte Carlo of its own: the comparison's figure never re-runs it
    output:
        csv=f"{OUT}/tables/procrustes_deflation.csv",
    log:
        f"{OUT}/logs/procrustes_deflation.log",
    benchmark:
        f"{OUT}/benchmarks/procrustes_deflation.tsv"
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("procrustes_deflation"),
    params:
        trials=config["astrometry"]["trials"],
        code=code_version("reproduction"),
    script:
        "../scripts/procrustes_deflation.py"


rule paper_comparison:
    input:
        unpack(comparison_inputs),
    output:
        csv=f"{OUT}/tables/paper_comparison.csv",
        png=report(
            f"{OUT}/figures/paper_comparison.png",
            category="Paper comparison",
            caption="../report/paper_comparison.rst",
        ),
        pdf=f"{OUT}/figures/paper_comparison.pdf",
    log:
        f"{OUT}/logs/paper_comparison.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("paper_comparison"),
    params:
        code=code_version("reproduction", "plotting", "io"),
        dataset=MANIFEST.name,
        positions=config["astrometry"]["positions"],
        method=config["centroids"]["method"],  # the method of centroids/<mode>.nc
    script:
        "../scripts/paper_comparison.py"


rule paper_pdf:
    input:
        figures=lambda w: [png for png, _ in paper_pdf_pages()],
        captions=lambda w: [caption for _, caption in paper_pdf_pages()],  # an edited caption rebuilds it
        comparison=rules.paper_comparison.output.csv,
    output:
        pdf=f"{OUT}/report/paper_reproduction.pdf",
    log:
        f"{OUT}/logs/paper_pdf.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("paper_pdf"),
    params:
        dataset=MANIFEST.name,
        code=code_version("plotting"),
    script:
        "../scripts/paper_pdf.py"


rule paper:
    input:
        rules.paper_pdf.output,
        calibration_targets(),
        metrology_targets(),
        centroid_targets(),
        astrometry_targets(),
        rules.plot_offset_bias.output,
        rules.error_propagation_table.output,
        rules.plot_error_propagation.output,
        rules.paper_comparison.output,
        [f"{SWEEP_ROOT}/{paper_sweep(study)}/summary.csv" for study in ("offset_bias", "error_propagation")],
