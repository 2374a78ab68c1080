# Pseudo stars: each position's frames read once into its mean and batch means
# (stars/<index>.nc), then centroids from those, one product per calibration mode
# (config centroids.modes) and method (centroids.methods).


rule stack_position:
    input:
        manifest=MANIFEST_FILE,
        cubes=position_files,
    output:
        stack=f"{OUT}/stars/{{position}}.nc",
    params:
        batches=config["centroids"]["batches"],
        code=code_version("io", "manifest", "stacks"),
        roots=ROOTS,  # inputs are recorded relative to these
    log:
        f"{OUT}/logs/stack_position_{{position}}.log",
    benchmark:
        f"{OUT}/benchmarks/stack_position_{{position}}.tsv"
    conda:
        "../envs/dice.yaml"
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
    params:
        code=code_version("io", "manifest", "calibration", "centroids", "polynomials", "stacks"),
        roots=ROOTS,  # inputs are recorded relative to these
        options=centroid_options,
    log:
        f"{OUT}/logs/measure_centroids_{{mode}}.log",
    benchmark:
        f"{OUT}/benchmarks/measure_centroids_{{mode}}.tsv"
    conda:
        "../envs/dice.yaml"
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
        png=report(f"{OUT}/figures/centroids_{{mode}}.png", category="Pseudo stars",
                   caption="../report/centroids.rst"),
        pdf=f"{OUT}/figures/centroids_{{mode}}.pdf",
    params:
        code=code_version("plotting", "io"),
        positions=config["astrometry"]["positions"],  # the used range, marked red
    log:
        f"{OUT}/logs/plot_centroids_{{mode}}.log",
    conda:
        "../envs/dice.yaml"
    script:
        "../scripts/plot_centroids.py"
