# Simulated testbed (only when config dataset names a preset): truth first, then
# one job per FITS file (the star positions' files one job per group of positions,
# as their stacks), then the manifest that makes it a dataset. Their settings are
# the preset with config simulation's overrides, handed over whole.

if SIMULATE:
    SIM_CONFIG = SIMULATION.to_dict()
    SIM_FILES = list(simulation.file_jobs(SIMULATION))

    rule simulate_truth:
        output:
            truth=output_of("truth"),
        log:
            f"{OUT}/logs/simulate_truth.log",
        conda:
            "../envs/dice.yaml"
        resources:
            **step_resources("simulate_truth"),
        params:
            **step_params("simulate_truth", simulation=SIM_CONFIG),
        script:
            "../scripts/simulate_truth.py"

    rule simulate_file:
        input:
            truth=rules.simulate_truth.output.truth,
        output:
            cube=output_of("cube"),
        log:
            f"{OUT}/logs/simulate/{{relpath}}.log",
        benchmark:
            f"{OUT}/benchmarks/simulate/{{relpath}}.tsv"
        wildcard_constraints:
            relpath="(dark|flat|metrology)/[A-Za-z0-9._-]+",
        conda:
            "../envs/dice.yaml"
        resources:
            **step_resources("simulate_file"),
        params:
            **step_params("simulate_file", simulation=SIM_CONFIG),
        script:
            "../scripts/simulate_file.py"

    for _group in POSITION_GROUPS:

        rule:
            name:
                steps.group_rule("simulate_file", _group)
            input:
                truth=rules.simulate_truth.output.truth,
            output:
                cubes=group_files(_group),
            log:
                f"{OUT}/logs/simulate/{steps.group_rule('simulate_file', _group)}.log",
            benchmark:
                f"{OUT}/benchmarks/simulate/{steps.group_rule('simulate_file', _group)}.tsv"
            conda:
                "../envs/dice.yaml"
            resources:
                **step_resources("simulate_file", relpaths=group_files(_group)),
            params:
                **step_params("simulate_file", simulation=SIM_CONFIG),
            script:
                "../scripts/simulate_file.py"

    rule simulate_manifest:
        input:
            truth=rules.simulate_truth.output.truth,
            cubes=[f"{RAW}/{f}" for f in SIM_FILES],
        output:
            manifest=output_of("manifest"),
        log:
            f"{OUT}/logs/simulate_manifest.log",
        conda:
            "../envs/dice.yaml"
        resources:
            **step_resources("simulate_manifest"),
        params:
            **step_params("simulate_manifest", simulation=SIM_CONFIG),
        script:
            "../scripts/simulate_manifest.py"
