# Simulated testbed (only when config dataset names a preset): truth first, then
# one job per FITS file, then the manifest that makes it a dataset.

if SIMULATE:
    SIM_CONFIG = SIMULATION.to_dict()
    SIM_FILES = list(simulation.file_jobs(SIMULATION))

    rule simulate_truth:
        output:
            truth=f"{RAW}/truth.nc",
        log:
            f"{OUT}/logs/simulate_truth.log",
        conda:
            "../envs/dice.yaml"
        resources:
            **step_resources("simulate_truth"),
        params:
            simulation=SIM_CONFIG,
            code=code_version("detector", "geometry", "simulation", "io", "polynomials"),
        script:
            "../scripts/simulate_truth.py"

    rule simulate_file:
        input:
            truth=rules.simulate_truth.output.truth,
        output:
            cube=f"{RAW}/{{relpath}}.fits",
        log:
            f"{OUT}/logs/simulate/{{relpath}}.log",
        benchmark:
            f"{OUT}/benchmarks/simulate/{{relpath}}.tsv"
        wildcard_constraints:
            relpath="(dark|flat|metrology|stars)/[A-Za-z0-9._-]+",
        conda:
            "../envs/dice.yaml"
        resources:
            **step_resources("simulate_file"),
        params:
            simulation=SIM_CONFIG,
            code=code_version("detector", "geometry", "simulation", "io", "polynomials"),
        script:
            "../scripts/simulate_file.py"

    rule simulate_manifest:
        input:
            truth=rules.simulate_truth.output.truth,
            cubes=[f"{RAW}/{f}" for f in SIM_FILES],
        output:
            manifest=f"{RAW}/dataset.yaml",
        log:
            f"{OUT}/logs/simulate_manifest.log",
        conda:
            "../envs/dice.yaml"
        resources:
            **step_resources("simulate_manifest"),
        params:
            simulation=SIM_CONFIG,
            code=code_version("geometry", "simulation", "manifest"),
        script:
            "../scripts/simulate_manifest.py"
