# Pseudo stars: each position's frames read once into its mean and batch means
# (stars/<index>.nc), then centroids from those, one product per calibration mode
# (config centroids.modes) and method (centroids.methods).


# One stack job a group of consecutive positions (config job_samples, docs/running.md "Jobs").
for _group in POSITION_GROUPS:

    rule:
        name:
            steps.group_rule("stack_position", _group)
        input:
            manifest=MANIFEST_FILE,
            cubes=group_inputs("stack_position", _group),
        output:
            stacks=[output_of("stack", position=index) for index in _group],
        log:
            f"{OUT}/logs/{steps.group_rule('stack_position', _group)}.log",
        benchmark:
            f"{OUT}/benchmarks/{steps.group_rule('stack_position', _group)}.tsv"
        conda:
            "../envs/dice.yaml"
        resources:
            **step_resources("stack_position", positions=_group),
        params:
            **step_params("stack_position", positions=list(_group)),
        script:
            "../scripts/stack_position.py"


rule measure_centroids:
    input:
        unpack(lambda w: PLAN.centroid_calibrations(w.mode)),
        manifest=MANIFEST_FILE,
        dark=output_of("dark"),
        stacks=position_stacks,
    output:
        centroids=output_of("centroids"),
    log:
        f"{OUT}/logs/measure_centroids_{{mode}}.log",
    benchmark:
        f"{OUT}/benchmarks/measure_centroids_{{mode}}.tsv"
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("measure_centroids"),
    params:
        **step_params("measure_centroids", method=config["centroids"]["method"]),
    script:
        "../scripts/measure_centroids.py"


# each other method of centroids.methods: the same step, its method from the path
use rule measure_centroids as measure_centroids_by_method with:
    output:
        centroids=output_of("centroids_by_method"),
    log:
        f"{OUT}/logs/measure_centroids_{{method}}_{{mode}}.log",
    benchmark:
        f"{OUT}/benchmarks/measure_centroids_{{method}}_{{mode}}.tsv"
    params:
        **step_params("measure_centroids_by_method", method=lambda w: w.method),


rule plot_centroids:
    input:
        centroids=output_of("centroids"),
    output:
        **figure_of("figure_centroids", category="Pseudo stars", caption="centroids"),
    log:
        f"{OUT}/logs/plot_centroids_{{mode}}.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("plot_centroids"),
    params:
        **step_params("plot_centroids"),
    script:
        "../scripts/plot_centroids.py"
