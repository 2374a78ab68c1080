"""Snakemake step: one point of a sweep (config sweeps), a simulation study with known truth."""

from pathlib import Path

import dice_core
from dice_core import io, studies


def sweep_point(output, study, parameters, bench, options, sweep, config):
    ds = studies.run_point(study, parameters, bench=bench, options=options, workdir=Path(output).parent)
    ds.attrs["sweep"] = sweep
    io.write_product(ds, output, title=f"sweep {sweep}, study {study}, point {parameters}",
                     config=config)  # the point's parameters: the attribute "point" (studies.sweep_dataset)


spec = snakemake.params.settings["sweeps"][snakemake.wildcards.sweep]
dice_core.run_logged(snakemake.log[0], sweep_point, snakemake.output.point, spec["study"],
                     dict(snakemake.params.parameters), dict(spec["bench"]), dict(spec["options"]),
                     snakemake.wildcards.sweep, snakemake.params.settings,
                     provenance={"code_version": snakemake.params.code})
