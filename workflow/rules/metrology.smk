# Metrology stage: global fringe solution per baseline, deprojection per pair,
# and each other pair's difference from the reference pair.


# threads: worker processes reading parts of the frames, one BLAS thread each (dice_core.parallel).
rule fit_fringes:
    threads: 2
    input:
        manifest=MANIFEST_FILE,
        dark=rules.measure_dark.output.dark,
        prnu=prnu_for_metrology,
        bad_pixels=bad_pixel_mask,
        cubes=baseline_files,
    output:
        metrology=f"{OUT}/metrology/{{baseline}}.nc",
    params:
        code=code_version("io", "manifest", "calibration", "fringes", "geometry", "parallel", "polynomials"),
        roots=ROOTS,  # inputs are recorded relative to these
        options=config["metrology"],  # a changed option (tip_sigma, tolerance...) reruns the fits
    log:
        f"{OUT}/logs/fit_fringes_{{baseline}}.log",
    benchmark:
        f"{OUT}/benchmarks/fit_fringes_{{baseline}}.tsv"
    conda:
        "../envs/dice.yaml"
    script:
        "../scripts/fit_fringes.py"


rule deproject_offsets:
    input:
        first=lambda w: f"{OUT}/metrology/{pair_baselines(w)[0]}.nc",
        second=lambda w: f"{OUT}/metrology/{pair_baselines(w)[1]}.nc",
    output:
        offsets=f"{OUT}/calibration/offsets_{{pair}}.nc",
    params:
        baselines=pair_baselines,
        code=code_version("io", "deprojection", "geometry"),
        roots=ROOTS,  # inputs are recorded relative to these
    log:
        f"{OUT}/logs/deproject_offsets_{{pair}}.log",
    conda:
        "../envs/dice.yaml"
    script:
        "../scripts/deproject_offsets.py"


rule compare_pairs:
    input:
        reference=f"{OUT}/calibration/offsets_{MANIFEST.reference_pair}.nc",
        other=f"{OUT}/calibration/offsets_{{pair}}.nc",
    output:
        difference=f"{OUT}/calibration/offsets_difference_{{pair}}.nc",
    params:
        reference=MANIFEST.reference_pair,
        code=code_version("io", "deprojection", "geometry"),
        roots=ROOTS,  # inputs are recorded relative to these
    log:
        f"{OUT}/logs/compare_pairs_{{pair}}.log",
    conda:
        "../envs/dice.yaml"
    script:
        "../scripts/compare_pairs.py"


rule allan_deviation:
    threads: 2
    input:
        manifest=MANIFEST_FILE,
        metrology=rules.fit_fringes.output.metrology,
        dark=rules.measure_dark.output.dark,
        cubes=baseline_files,
    output:
        allan=f"{OUT}/allan/{{baseline}}.nc",
    params:
        code=code_version("io", "manifest", "allan", "fringes", "geometry", "parallel", "polynomials"),
        roots=ROOTS,  # inputs are recorded relative to these
    log:
        f"{OUT}/logs/allan_deviation_{{baseline}}.log",
    benchmark:
        f"{OUT}/benchmarks/allan_deviation_{{baseline}}.tsv"
    conda:
        "../envs/dice.yaml"
    script:
        "../scripts/allan_deviation.py"
