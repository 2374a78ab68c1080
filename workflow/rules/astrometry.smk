# Differential astrometry: accuracies of every centroid mode under each superimposition (Procrustes, and the
# projective and pose models of astrometry.superimposition), gathered in one table.


rule accuracy_table:
    input:
        centroids=centroid_products,
    output:
        csv=f"{OUT}/tables/accuracy.csv",
        tex=f"{OUT}/tables/accuracy.tex",
        residuals=f"{OUT}/tables/procrustes_residuals.nc",
        model_residuals=[f"{OUT}/tables/{model}_residuals.nc" for model in extra_superimpositions()],
    log:
        f"{OUT}/logs/accuracy_table.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("accuracy_table"),
    params:
        roots=ROOTS,  # inputs are recorded relative to these
        code=code_version("io", "superimposition", "accuracies"),
        options=lambda w: config["astrometry"],
        models=extra_superimpositions(),
    script:
        "../scripts/accuracy_table.py"


rule plot_procrustes_residuals:
    input:
        residuals=rules.accuracy_table.output.residuals,
    output:
        png=report(
            f"{OUT}/figures/procrustes_residuals.png",
            category="Astrometry",
            caption="../report/procrustes_residuals.rst",
        ),
        pdf=f"{OUT}/figures/procrustes_residuals.pdf",
        barycentre_png=report(
            f"{OUT}/figures/barycentre_residuals.png",
            category="Astrometry",
            caption="../report/barycentre_residuals.rst",
        ),
        barycentre_pdf=f"{OUT}/figures/barycentre_residuals.pdf",
    log:
        f"{OUT}/logs/plot_procrustes_residuals.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_procrustes_residuals"),
    params:
        code=code_version("plotting", "io"),
    script:
        "../scripts/plot_procrustes_residuals.py"


rule plot_superimposition_residuals:
    input:
        residuals=f"{OUT}/tables/{{model}}_residuals.nc",
    output:
        png=report(
            f"{OUT}/figures/{{model}}_residuals.png",
            category="Astrometry",
            caption="../report/superimposition_residuals.rst",
        ),
        pdf=f"{OUT}/figures/{{model}}_residuals.pdf",
    log:
        f"{OUT}/logs/plot_{{model}}_residuals.log",
    wildcard_constraints:
        model="projective|pose",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_superimposition_residuals"),
    params:
        code=code_version("plotting", "io"),
    script:
        "../scripts/plot_superimposition_residuals.py"
