# Differential astrometry: accuracies of every centroid mode under each superimposition (Procrustes, and the
# projective and pose models of astrometry.superimposition), gathered in one table.


rule accuracy_table:
    input:
        centroids=lambda w: PLAN.centroid_products(),
    output:
        csv=output_of("accuracy_table"),
        tex=output_of("accuracy_latex"),
        residuals=output_of("procrustes_residuals"),
        model_residuals=[PLAN.path("model_residuals", model=model) for model in PLAN.extra_superimpositions()],
    log:
        f"{OUT}/logs/accuracy_table.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("accuracy_table"),
    params:
        **step_params("accuracy_table", models=PLAN.extra_superimpositions()),
    script:
        "../scripts/accuracy_table.py"


rule plot_procrustes_residuals:
    input:
        residuals=output_of("procrustes_residuals"),
    output:
        **figure_of("figure_procrustes_residuals", category="Astrometry", caption="procrustes_residuals"),
        **figure_of("figure_barycentre_residuals", "barycentre_", category="Astrometry", caption="barycentre_residuals"),
    log:
        f"{OUT}/logs/plot_procrustes_residuals.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_procrustes_residuals"),
    params:
        **step_params("plot_procrustes_residuals"),
    script:
        "../scripts/plot_procrustes_residuals.py"


rule plot_superimposition_residuals:
    input:
        residuals=output_of("model_residuals"),
    output:
        **figure_of("figure_model_residuals", category="Astrometry", caption="superimposition_residuals"),
    log:
        f"{OUT}/logs/plot_{{model}}_residuals.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_superimposition_residuals"),
    params:
        **step_params("plot_superimposition_residuals"),
    script:
        "../scripts/plot_superimposition_residuals.py"
