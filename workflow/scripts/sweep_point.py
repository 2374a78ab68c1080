"""Snakemake step: one point of a sweep (config sweeps), a simulation study with known truth."""

from pathlib import Path

import dice_core
from dice_core import io, studies


def sweep_point(output, study, parameters, bench, options, sweep, config):
    ds = studies.run_point(study, parameters, bench=bench, options=options, workdir=Path(output).parent)
    ds.attrs["sweep"] = sweep
    io.write_product(ds, output, title=f"sweep {sweep}, study {study}, point {parameters}",
                     config={"sweep": config["sweeps"][sweep], "point": parameters})


dice_core.run_logged(snakemake.log[0], sweep_point, snakemake.output.point, snakemake.params.study,
                     dict(snakemake.params.parameters), dict(snakemake.params.bench), dict(snakemake.params.options),
                     snakemake.wildcards.sweep, snakemake.config, provenance={"code_version": snakemake.params.code})
