# Dark and flat-field stages: dark maps, one PRNU map per flat, the reference
# PRNU, and each other flat's difference from it.


rule measure_dark:
    input:
        manifest=MANIFEST_FILE,
        cubes=acquisition_files(MANIFEST.dark) if MANIFEST.dark else [],
    output:
        dark=f"{OUT}/calibration/dark.nc",
    log:
        f"{OUT}/logs/measure_dark.log",
    benchmark:
        f"{OUT}/benchmarks/measure_dark.tsv"
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("measure_dark"),
    params:
        roots=ROOTS,  # inputs are recorded relative to these
        code=code_version("io", "manifest", "calibration", "polynomials"),
    script:
        "../scripts/measure_dark.py"


rule measure_prnu:
    input:
        manifest=MANIFEST_FILE,
        dark=rules.measure_dark.output.dark,
        cubes=flat_files,
    output:
        prnu=f"{OUT}/calibration/flats/prnu_{{flat}}.nc",
    log:
        f"{OUT}/logs/measure_prnu_{{flat}}.log",
    benchmark:
        f"{OUT}/benchmarks/measure_prnu_{{flat}}.tsv"
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("measure_prnu"),
    params:
        roots=ROOTS,  # inputs are recorded relative to these
        code=code_version("io", "manifest", "calibration", "polynomials"),
    script:
        "../scripts/measure_prnu.py"


rule select_reference_prnu:
    input:
        prnu=f"{OUT}/calibration/flats/prnu_{MANIFEST.reference_flat}.nc",
    output:
        prnu=f"{OUT}/calibration/prnu.nc",
    log:
        f"{OUT}/logs/select_reference_prnu.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("select_reference_prnu"),
    params:
        roots=ROOTS,  # inputs are recorded relative to these
        reference=MANIFEST.reference_flat,
        code=code_version("io"),
    script:
        "../scripts/select_reference_prnu.py"


rule compare_prnu:
    input:
        reference=rules.select_reference_prnu.output.prnu,
        other=f"{OUT}/calibration/flats/prnu_{{flat}}.nc",
        manifest=MANIFEST_FILE,
    output:
        difference=f"{OUT}/calibration/prnu_difference_{{flat}}.nc",
    log:
        f"{OUT}/logs/compare_prnu_{{flat}}.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("compare_prnu"),
    params:
        roots=ROOTS,  # inputs are recorded relative to these
        code=code_version("io", "manifest", "calibration", "polynomials"),
    script:
        "../scripts/compare_prnu.py"


rule find_bad_pixels:
    input:
        manifest=MANIFEST_FILE,
        dark=rules.measure_dark.output.dark,
        prnu=rules.select_reference_prnu.output.prnu,
    output:
        bad_pixels=f"{OUT}/calibration/bad_pixels.nc",
    log:
        f"{OUT}/logs/find_bad_pixels.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("find_bad_pixels"),
    params:
        roots=ROOTS,  # inputs are recorded relative to these
        code=code_version("io", "manifest", "calibration", "polynomials"),
    script:
        "../scripts/find_bad_pixels.py"
