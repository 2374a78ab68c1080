# Metrology stage: global fringe solution per baseline, deprojection per pair,
# and each other pair's difference from the reference pair.


SPLIT = f"{OUT}/metrology/split/{{baseline}}"
PASSES = config["metrology"]["max_passes"]


if config["metrology"]["split"]:

    # One baseline's fit as jobs (docs/metrology.md, "Splitting a fit across jobs"): the state before
    # pass 1, then per pass one job per part of the files and one that sums them in part order, and the
    # product. A fixed number of passes (max_passes): those after convergence carry the state over.
    rule fit_start:
        input:
            manifest=MANIFEST_FILE,
            dark=rules.measure_dark.output.dark,
            prnu=prnu_for_metrology,
            bad_pixels=bad_pixel_mask,
            cubes=baseline_files,
        output:
            state=temp(f"{SPLIT}/state_0.nc"),
        log:
            f"{OUT}/logs/fit_start_{{baseline}}.log",
        benchmark:
            f"{OUT}/benchmarks/fit_start_{{baseline}}.tsv"
        conda:
            "../envs/dice.yaml"
        resources:
            **step_resources("fit_start"),
        params:
            roots=ROOTS,  # inputs are recorded relative to these
            code=code_version("io", "manifest", "calibration", "fringe_fit"),
            options=config["metrology"],  # the fit's options are the state's
            chunk_frames=config["chunk_frames"],  # the reference frame is the first chunk's mean
        script:
            "../scripts/fit_start.py"

    rule fit_part:
        input:
            manifest=MANIFEST_FILE,
            state=lambda w: f"{OUT}/metrology/split/{w.baseline}/state_{int(w.npass) - 1}.nc",
            # its own group of files only: it reads no other samples (the others' headers, which every job of
            # the fit reads, exist once fit_start has run)
            cubes=part_files,
            # pass 1's part, which recorded its files' checksums: later passes do not read them again for it
            first=lambda w: [f"{OUT}/metrology/split/{w.baseline}/pass_1/part_{w.part}.nc"] if int(w.npass) > 1 else [],
        output:
            # small (25 bytes a pixel), but one per part and pass: removed once the passes that need it have run
            part=temp(f"{SPLIT}/pass_{{npass}}/part_{{part}}.nc"),
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
            roots=ROOTS,  # inputs are recorded relative to these
            code=code_version("io", "manifest", "fringe_fit"),
            parts=config["metrology"]["parts"],
            chunk_frames=config["chunk_frames"],
        script:
            "../scripts/fit_part.py"

    rule fit_reduce:
        input:
            state=lambda w: f"{OUT}/metrology/split/{w.baseline}/state_{int(w.npass) - 1}.nc",
            parts=lambda w: [
                f"{OUT}/metrology/split/{w.baseline}/pass_{w.npass}/part_{part}.nc"
                for part in range(config["metrology"]["parts"])
            ],
        output:
            state=temp(f"{SPLIT}/state_{{npass}}.nc"),
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
            roots=ROOTS,  # inputs are recorded relative to these
            code=code_version("io", "fringe_fit"),
        script:
            "../scripts/fit_reduce.py"

    rule fit_finish:
        input:
            manifest=MANIFEST_FILE,
            dark=rules.measure_dark.output.dark,
            prnu=prnu_for_metrology,
            bad_pixels=bad_pixel_mask,
            state=f"{SPLIT}/state_{PASSES}.nc",
            # not read (their checksums come from pass 1's parts), but declared: the states and parts are
            # temporary, so this job is what a changed cube makes rerun, and with it the passes
            cubes=baseline_files,
            first=lambda w: [
                f"{OUT}/metrology/split/{w.baseline}/pass_1/part_{part}.nc"
                for part in range(config["metrology"]["parts"])
            ],
        output:
            metrology=f"{OUT}/metrology/{{baseline}}.nc",
        log:
            f"{OUT}/logs/fit_finish_{{baseline}}.log",
        benchmark:
            f"{OUT}/benchmarks/fit_finish_{{baseline}}.tsv"
        conda:
            "../envs/dice.yaml"
        resources:
            **step_resources("fit_finish"),
        params:
            roots=ROOTS,  # inputs are recorded relative to these
            # the code, scripts and settings of every step of the split fit: its states and parts are temporary,
            # so a change to any of them must rerun this job (and through its missing inputs, the passes)
            code=code_version("io", "manifest", "calibration", "fringes", "fringe_fit", "geometry"),
            scripts=script_version("fit_start", "fit_part", "fit_reduce"),
            options=config["metrology"],
            chunk_frames=config["chunk_frames"],
        script:
            "../scripts/fit_finish.py"

else:

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
            code=code_version(
                "io", "manifest", "calibration", "fringes", "fringe_fit", "geometry", "parallel", "polynomials"
            ),
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
        manifest=MANIFEST_FILE,  # names the pair in errors
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
        metrology=f"{OUT}/metrology/{{baseline}}.nc",
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
