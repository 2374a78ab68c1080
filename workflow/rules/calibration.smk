# Dark and flat-field stages: dark maps, one PRNU map per flat, the reference
# PRNU, and each other flat's difference from it.


rule measure_dark:
    input:
        manifest=MANIFEST_FILE,
        cubes=acquisition_files(MANIFEST.dark) if MANIFEST.dark else [],
    output:
        dark=output_of("dark"),
    log:
        f"{OUT}/logs/measure_dark.log",
    benchmark:
        f"{OUT}/benchmarks/measure_dark.tsv"
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("measure_dark"),
    params:
        **step_params("measure_dark"),
    script:
        "../scripts/measure_dark.py"


rule measure_prnu:
    input:
        manifest=MANIFEST_FILE,
        dark=output_of("dark"),
        cubes=flat_files,
    output:
        prnu=output_of("flat_prnu"),
    log:
        f"{OUT}/logs/measure_prnu_{{flat}}.log",
    benchmark:
        f"{OUT}/benchmarks/measure_prnu_{{flat}}.tsv"
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("measure_prnu"),
    params:
        **step_params("measure_prnu"),
    script:
        "../scripts/measure_prnu.py"


rule select_reference_prnu:
    input:
        prnu=PLAN.path("flat_prnu", flat=MANIFEST.reference_flat) if MANIFEST.flats else [],
    output:
        prnu=output_of("prnu"),
    log:
        f"{OUT}/logs/select_reference_prnu.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("select_reference_prnu"),
    params:
        **step_params("select_reference_prnu", reference=MANIFEST.reference_flat),
    script:
        "../scripts/select_reference_prnu.py"


rule compare_prnu:
    input:
        reference=lambda w: PLAN.prnu_compared_with(w.flat),
        other=output_of("flat_prnu"),
        manifest=MANIFEST_FILE,
    output:
        difference=output_of("prnu_difference"),
    log:
        f"{OUT}/logs/compare_prnu_{{flat}}.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("compare_prnu"),
    params:
        **step_params("compare_prnu"),
    script:
        "../scripts/compare_prnu.py"


rule find_bad_pixels:
    input:
        manifest=MANIFEST_FILE,
        dark=output_of("dark"),
        prnu=output_of("prnu"),
    output:
        bad_pixels=output_of("bad_pixels"),
    log:
        f"{OUT}/logs/find_bad_pixels.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("find_bad_pixels"),
    params:
        **step_params("find_bad_pixels"),
    script:
        "../scripts/find_bad_pixels.py"
