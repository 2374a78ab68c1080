# Metrology stage: global fringe solution per baseline, deprojection per pair,
# and each other pair's difference from the reference pair.


PASSES = config["metrology"]["max_passes"]


if config["metrology"]["split"]:

    # One baseline's fit as jobs (docs/metrology.md, "Splitting a fit across jobs"): the state before
    # pass 1, then per pass one job per part of the files and one that sums them in part order, and the
    # product. A fixed number of passes (max_passes): those after convergence carry the state over.
    rule fit_start:
        input:
            manifest=MANIFEST_FILE,
            dark=output_of("dark"),
            prnu=lambda w: PLAN.prnu_for_metrology(w.baseline),
            bad_pixels=lambda w: PLAN.bad_pixel_mask(),
            cubes=baseline_files,
        output:
            state=temp(output_of("fit_state", npass=0)),
        log:
            f"{OUT}/logs/fit_start_{{baseline}}.log",
        benchmark:
            f"{OUT}/benchmarks/fit_start_{{baseline}}.tsv"
        conda:
            "../envs/dice.yaml"
        resources:
            **step_resources("fit_start"),
        params:
            **step_params("fit_start"),
        script:
            "../scripts/fit_start.py"

    rule fit_part:
        input:
            manifest=MANIFEST_FILE,
            state=lambda w: fit_state(w, int(w.npass) - 1),
            # its own group of files only: it reads no other samples (the others' headers, which every job of
            # the fit reads, exist once fit_start has run)
            cubes=part_files,
        output:
            # small (25 bytes a pixel), but one per part and pass: removed once the passes that need it have run
            part=temp(output_of("fit_part")),
        log:
            f"{OUT}/logs/fit_part_{{baseline}}_{{npass}}_{{part}}.log",
        benchmark:
            f"{OUT}/benchmarks/fit_part_{{baseline}}_{{npass}}_{{part}}.tsv"
        wildcard_constraints:
            npass="[1-9][0-9]*",
            part="[0-9]+",
        conda:
            "../envs/dice.yaml"
        resources:
            **step_resources("fit_part"),
        params:
            **step_params("fit_part"),
        script:
            "../scripts/fit_part.py"

    rule fit_reduce:
        input:
            state=lambda w: fit_state(w, int(w.npass) - 1),
            parts=lambda w: [fit_part_of(w, w.npass, part) for part in range(config["metrology"]["parts"])],
        output:
            state=temp(output_of("fit_state")),
        log:
            f"{OUT}/logs/fit_reduce_{{baseline}}_{{npass}}.log",
        benchmark:
            f"{OUT}/benchmarks/fit_reduce_{{baseline}}_{{npass}}.tsv"
        wildcard_constraints:
            npass="[1-9][0-9]*",
        conda:
            "../envs/dice.yaml"
        resources:
            **step_resources("fit_reduce"),
        params:
            **step_params("fit_reduce"),
        script:
            "../scripts/fit_reduce.py"

    rule fit_finish:
        input:
            manifest=MANIFEST_FILE,
            dark=output_of("dark"),
            prnu=lambda w: PLAN.prnu_for_metrology(w.baseline),
            bad_pixels=lambda w: PLAN.bad_pixel_mask(),
            state=lambda w: fit_state(w, PASSES),
            # not read (their checksums come from pass 1's parts), but declared: the states and parts are
            # temporary, so this job is what a changed cube makes rerun, and with it the passes
            cubes=baseline_files,
            first=lambda w: [fit_part_of(w, 1, part) for part in range(config["metrology"]["parts"])],
        output:
            metrology=output_of("metrology"),
        log:
            f"{OUT}/logs/fit_finish_{{baseline}}.log",
        benchmark:
            f"{OUT}/benchmarks/fit_finish_{{baseline}}.tsv"
        conda:
            "../envs/dice.yaml"
        resources:
            **step_resources("fit_finish"),
        params:
            # its step stands for every step of the split fit (dice_core.steps): their states and parts are
            # temporary, so a change to their settings or code must rerun this job (and the passes with it)
            **step_params("fit_finish"),
        script:
            "../scripts/fit_finish.py"

else:

    # threads: worker processes reading the metrology.parts parts of the frames, one BLAS thread each
    # (dice_core.parallel), for a large baseline only (dice_core.resources.reading_workers).
    rule fit_fringes:
        input:
            manifest=MANIFEST_FILE,
            dark=output_of("dark"),
            prnu=lambda w: PLAN.prnu_for_metrology(w.baseline),
            bad_pixels=lambda w: PLAN.bad_pixel_mask(),
            cubes=baseline_files,
        output:
            metrology=output_of("metrology"),
        log:
            f"{OUT}/logs/fit_fringes_{{baseline}}.log",
        benchmark:
            f"{OUT}/benchmarks/fit_fringes_{{baseline}}.tsv"
        conda:
            "../envs/dice.yaml"
        threads: reading_threads(config["metrology"]["parts"])
        resources:
            **step_resources("fit_fringes"),
        params:
            **step_params("fit_fringes"),
        script:
            "../scripts/fit_fringes.py"


rule prf_widths:
    input:
        manifest=MANIFEST_FILE,
        dark=output_of("dark"),
        metrology=lambda w: PLAN.metrology_products(),
    output:
        prf=output_of("prf"),
    log:
        f"{OUT}/logs/prf_widths.log",
    benchmark:
        f"{OUT}/benchmarks/prf_widths.tsv"
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("prf_widths"),
    params:
        **step_params("prf_widths"),
    script:
        "../scripts/prf_widths.py"


# Each baseline's offset spectrum and the coherent stray light it shows (metrology.stray_light: detect or remove).
rule find_stray_light:
    input:
        metrology=output_of("metrology"),
    output:
        stray=output_of("stray_light"),
    log:
        f"{OUT}/logs/find_stray_light_{{baseline}}.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("find_stray_light"),
    params:
        **step_params("find_stray_light"),
    script:
        "../scripts/find_stray_light.py"


# Several wavelengths (format 1.2): every wavelength's reference pair's offsets, PRF widths and laser flat
# gathered into one calibration across wavelength (docs/centroids.md, "Chromatic pixels").
rule chromatic_calibration:
    input:
        manifest=MANIFEST_FILE,
        dark=output_of("dark"),
        offsets=lambda w: PLAN.chromatic_inputs()["offsets"],
        metrology=lambda w: PLAN.chromatic_inputs()["metrology"],
        flats=lambda w: PLAN.chromatic_inputs()["flats"],
    output:
        chromatic=output_of("chromatic"),
    log:
        f"{OUT}/logs/chromatic_calibration.log",
    benchmark:
        f"{OUT}/benchmarks/chromatic_calibration.tsv"
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("chromatic_calibration"),
    params:
        **step_params("chromatic_calibration"),
    script:
        "../scripts/chromatic_calibration.py"


rule deproject_offsets:
    input:
        first=lambda w: PLAN.path("metrology", baseline=pair_baselines(w)[0]),
        second=lambda w: PLAN.path("metrology", baseline=pair_baselines(w)[1]),
        manifest=MANIFEST_FILE,  # names the pair in errors
        # with metrology.stray_light: remove, the components found in its two baselines
        stray=lambda w: PLAN.stray_light_removed(w.pair),
    output:
        offsets=output_of("offsets"),
    log:
        f"{OUT}/logs/deproject_offsets_{{pair}}.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("deproject_offsets"),
    params:
        **step_params("deproject_offsets", baselines=pair_baselines),
    script:
        "../scripts/deproject_offsets.py"


rule compare_pairs:
    input:
        reference=lambda w: PLAN.path("offsets", pair=PLAN.compared_pairs()[w.pair]),
        other=output_of("offsets"),
    output:
        difference=output_of("offsets_difference"),
    log:
        f"{OUT}/logs/compare_pairs_{{pair}}.log",
    conda:
        "../envs/dice.yaml"
    resources:
        **step_resources("compare_pairs"),
    params:
        **step_params("compare_pairs", reference=lambda w: PLAN.compared_pairs()[w.pair]),
    script:
        "../scripts/compare_pairs.py"


rule allan_deviation:
    input:
        manifest=MANIFEST_FILE,
        metrology=output_of("metrology"),
        dark=output_of("dark"),
        cubes=baseline_files,
    output:
        allan=output_of("allan"),
    log:
        f"{OUT}/logs/allan_deviation_{{baseline}}.log",
    benchmark:
        f"{OUT}/benchmarks/allan_deviation_{{baseline}}.tsv"
    conda:
        "../envs/dice.yaml"
    threads: reading_threads(LANES)  # the Allan step reads a baseline in LANES parts
    resources:
        **step_resources("allan_deviation"),
    params:
        **step_params("allan_deviation"),
    script:
        "../scripts/allan_deviation.py"
