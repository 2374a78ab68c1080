# Metrology stage: global fringe solution per baseline, deprojection per pair,
# and each other pair's difference from the reference pair.


# threads: worker processes reading parts of the frames, one BLAS thread each (dice_core.parallel).
rule fit_fringes:
    input:
        manifest=MANIFEST_FILE,
        dark=rules.measure_dark.output.dark,
        prnu=prnu_for_metrology,
        bad_pixels=bad_pixel_mask,
        cubes=baseline_files,
    output:
        metrology=f"{OUT}/metrology/{{baseline}}.nc",
    log:
        f"{OUT}/logs/fit_fringes_{{baseline}}.log",
    benchmark:
        f"{OUT}/benchmarks/fit_fringes_{{baseline}}.tsv"
    conda:
        "../envs/dice.yaml"
    threads: 2
    resources:
        **step_resources("fit_fringes"),
    params:
        roots=ROOTS,  # inputs are recorded relative to these
        code=code_version("io", "manifest", "calibration", "fringes", "geometry", "parallel", "polynomials"),
        options=config["metrology"],  # a changed option (tip_sigma, tolerance...) reruns the fits
    script:
        "../scripts/fit_fringes.py"


rule prf_widths:
    input:
        manifest=MANIFEST_FILE,
        dark=rules.measure_dark.output.dark,
        metrology=metrology_products,
    output:
        prf=f"{OUT}/calibration/prf.nc",
    log:
        f"{OUT}/logs/prf_widths.log",
    benchmark:
        f"{OUT}/benchmarks/prf_widths.tsv"
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("prf_widths"),
    params:
        code=code_version("io", "manifest", "prf"),
        options=config["prf"],  # the assumed kernel
        smooth_degree=config["metrology"]["smooth_degree"],
    script:
        "../scripts/prf_widths.py"


rule deproject_offsets:
    input:
        first=lambda w: f"{OUT}/metrology/{pair_baselines(w)[0]}.nc",
        second=lambda w: f"{OUT}/metrology/{pair_baselines(w)[1]}.nc",
    output:
        offsets=f"{OUT}/calibration/offsets_{{pair}}.nc",
    log:
        f"{OUT}/logs/deproject_offsets_{{pair}}.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("deproject_offsets"),
    params:
        roots=ROOTS,  # inputs are recorded relative to these
        baselines=pair_baselines,
        code=code_version("io", "deprojection", "geometry"),
    script:
        "../scripts/deproject_offsets.py"


rule compare_pairs:
    input:
        reference=f"{OUT}/calibration/offsets_{MANIFEST.reference_pair}.nc",
        other=f"{OUT}/calibration/offsets_{{pair}}.nc",
    output:
        difference=f"{OUT}/calibration/offsets_difference_{{pair}}.nc",
    log:
        f"{OUT}/logs/compare_pairs_{{pair}}.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("compare_pairs"),
    params:
        roots=ROOTS,  # inputs are recorded relative to these
        reference=MANIFEST.reference_pair,
        code=code_version("io", "deprojection", "geometry"),
    script:
        "../scripts/compare_pairs.py"


rule allan_deviation:
    input:
        manifest=MANIFEST_FILE,
        metrology=rules.fit_fringes.output.metrology,
        dark=rules.measure_dark.output.dark,
        cubes=baseline_files,
    output:
        allan=f"{OUT}/allan/{{baseline}}.nc",
    log:
        f"{OUT}/logs/allan_deviation_{{baseline}}.log",
    benchmark:
        f"{OUT}/benchmarks/allan_deviation_{{baseline}}.tsv"
    conda:
        "../envs/dice.yaml"
    threads: 2
    resources:
        **step_resources("allan_deviation"),
    params:
        roots=ROOTS,  # inputs are recorded relative to these
        code=code_version("io", "manifest", "allan", "fringes", "geometry", "parallel", "polynomials"),
    script:
        "../scripts/allan_deviation.py"
