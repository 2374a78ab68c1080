# Pseudo-star centroids, one product per calibration mode (config centroids.modes).


rule measure_centroids:
    input:
        unpack(centroid_calibrations),
        manifest=MANIFEST_FILE,
        dark=rules.measure_dark.output.dark,
        cubes=position_files,
    output:
        centroids=f"{OUT}/centroids/{{mode}}.nc",
    params:
        code=code_version("io", "manifest", "centroids"),
        # what a mode's product depends on: adding a mode to the list re-runs nothing else
        options=lambda w: {k: v for k, v in config["centroids"].items() if k != "modes"},
    log:
        f"{OUT}/logs/measure_centroids_{{mode}}.log",
    benchmark:
        f"{OUT}/benchmarks/measure_centroids_{{mode}}.tsv"
    conda:
        "../envs/dice.yaml"
    script:
        "../scripts/measure_centroids.py"


rule plot_centroids:
    input:
        centroids=rules.measure_centroids.output.centroids,
    output:
        png=report(f"{OUT}/figures/centroids_{{mode}}.png", category="Pseudo stars",
                   caption="../report/centroids.rst"),
        pdf=f"{OUT}/figures/centroids_{{mode}}.pdf",
    params:
        code=code_version("plotting", "io"),
    log:
        f"{OUT}/logs/plot_centroids_{{mode}}.log",
    conda:
        "../envs/dice.yaml"
    script:
        "../scripts/plot_centroids.py"
