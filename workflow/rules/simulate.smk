# Simulated testbed (only when config dataset names a preset): truth first, then
# the FITS files, one job per group of consecutive files (config job_samples),
# then the manifest that makes it a dataset. Their settings are the preset with
# config simulation's overrides, handed over whole.

if SIMULATE:
    SIM_CONFIG = SIMULATION.to_dict()

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

    for _group in SIM_GROUPS:

        rule:
            name:
                steps.group_rule("simulate_file", _group)
            input:
                truth=rules.simulate_truth.output.truth,
            output:
                cubes=group_inputs("simulate_file", _group),
            log:
                f"{OUT}/logs/simulate/{steps.group_rule('simulate_file', _group)}.log",
            benchmark:
                f"{OUT}/benchmarks/simulate/{steps.group_rule('simulate_file', _group)}.tsv"
            conda:
                "../envs/dice.yaml"
            resources:
                **step_resources("simulate_file", files=group_inputs("simulate_file", _group)),
            params:
                **step_params("simulate_file", simulation=SIM_CONFIG),
            script:
                "../scripts/simulate_file.py"

    rule simulate_manifest:
        input:
            truth=rules.simulate_truth.output.truth,
            cubes=[local_path(f) for f in MANIFEST.all_files()],
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
