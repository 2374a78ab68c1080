# Differential astrometry: Procrustes accuracies of every centroid mode, gathered in one table.


rule accuracy_table:
    input:
        centroids=centroid_products,
    output:
        csv=f"{OUT}/tables/accuracy.csv",
        tex=f"{OUT}/tables/accuracy.tex",
        residuals=f"{OUT}/tables/procrustes_residuals.nc",
    params:
        code=code_version("io", "astrometry"),
        roots=ROOTS,  # inputs are recorded relative to these
        options=lambda w: config["astrometry"],
    log:
        f"{OUT}/logs/accuracy_table.log",
    conda:
        "../envs/dice.yaml"
    script:
        "../scripts/accuracy_table.py"


rule plot_procrustes_residuals:
    input:
        residuals=rules.accuracy_table.output.residuals,
    output:
        png=report(f"{OUT}/figures/procrustes_residuals.png", category="Astrometry",
                   caption="../report/procrustes_residuals.rst"),
        pdf=f"{OUT}/figures/procrustes_residuals.pdf",
        barycentre_png=report(f"{OUT}/figures/barycentre_residuals.png", category="Astrometry",
                              caption="../report/barycentre_residuals.rst"),
        barycentre_pdf=f"{OUT}/figures/barycentre_residuals.pdf",
    params:
        code=code_version("plotting", "io"),
    log:
        f"{OUT}/logs/plot_procrustes_residuals.log",
    conda:
        "../envs/dice.yaml"
    script:
        "../scripts/plot_procrustes_residuals.py"
