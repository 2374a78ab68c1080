"""Snakemake step: simulate FITS files of the testbed dataset (a group of consecutive files: config job_samples)."""

from pathlib import Path

import dice_core
from dice_core import simulation
from dice_core.io import read_product


def simulate_files(settings, truth_path, outputs):
    """Simulate each of ``outputs`` (paths under the truth product's folder), one after the other."""
    cfg = simulation.SimulationConfig.from_dict(settings)
    raw = Path(truth_path).parent
    truth = read_product(truth_path)
    for output in outputs:
        simulation.write_file(cfg, truth, relpath=Path(output).relative_to(raw).as_posix(), outdir=raw)


dice_core.run_logged(snakemake.log[0], simulate_files, snakemake.params.simulation, snakemake.input.truth,
                     list(snakemake.output))
