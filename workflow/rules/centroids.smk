# Pseudo stars: each position's frames read once into its mean and batch means
# (stars/<index>.nc), then centroids from those, one product per calibration mode
# (config centroids.modes) and method (centroids.methods).


rule stack_position:
    input:
        manifest=MANIFEST_FILE,
        cubes=position_files,
    output:
        stack=f"{OUT}/stars/{{position}}.nc",
    log:
        f"{OUT}/logs/stack_position_{{position}}.log",
    benchmark:
        f"{OUT}/benchmarks/stack_position_{{position}}.tsv"
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("stack_position"),
    params:
        roots=ROOTS,  # inputs are recorded relative to these
        batches=config["centroids"]["batches"],
        code=code_version("io", "manifest", "stacks"),
    script:
        "../scripts/stack_position.py"


rule measure_centroids:
    input:
        unpack(centroid_calibrations),
        manifest=MANIFEST_FILE,
        dark=rules.measure_dark.output.dark,
        stacks=position_stacks,
    output:
        centroids=f"{OUT}/centroids/{{mode}}.nc",
    log:
        f"{OUT}/logs/measure_centroids_{{mode}}.log",
    benchmark:
        f"{OUT}/benchmarks/measure_centroids_{{mode}}.tsv"
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("measure_centroids"),
    params:
        roots=ROOTS,  # inputs are recorded relative to these
        code=code_version("io", "manifest", "calibration", "centroids", "polynomials", "stacks"),
        options=centroid_options,
    script:
        "../scripts/measure_centroids.py"


use rule measure_centroids as measure_centroids_by_method with:
    output:
        centroids=f"{OUT}/centroids/{{method}}/{{mode}}.nc",
    log:
        f"{OUT}/logs/measure_centroids_{{method}}_{{mode}}.log",
    benchmark:
        f"{OUT}/benchmarks/measure_centroids_{{method}}_{{mode}}.tsv"


rule plot_centroids:
    input:
        centroids=rules.measure_centroids.output.centroids,
    output:
        png=report(f"{OUT}/figures/centroids_{{mode}}.png", category="Pseudo stars", caption="../report/centroids.rst"),
        pdf=f"{OUT}/figures/centroids_{{mode}}.pdf",
    log:
        f"{OUT}/logs/plot_centroids_{{mode}}.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_centroids"),
    params:
        code=code_version("plotting", "io"),
        positions=config["astrometry"]["positions"],  # the used range, marked red
    script:
        "../scripts/plot_centroids.py"
