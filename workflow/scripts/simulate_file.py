"""Snakemake step: simulate one FITS file of the testbed dataset."""

from pathlib import Path

import dice_core
from dice_core import simulation
from dice_core.io import read_product


def simulate_file(settings, truth_path, output):
    cfg = simulation.SimulationConfig.from_dict(settings)
    raw = Path(truth_path).parent
    simulation.write_file(cfg, read_product(truth_path), relpath=Path(output).relative_to(raw).as_posix(), outdir=raw)


dice_core.run_logged(snakemake.log[0], simulate_file, snakemake.params.simulation, snakemake.input.truth,
                     snakemake.output.cube)
