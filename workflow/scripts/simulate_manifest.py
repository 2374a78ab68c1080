"""Snakemake step: write the simulated dataset's manifest, once all its files exist."""

from pathlib import Path

import dice_core
from dice_core import simulation
from dice_core.manifest import load_manifest


def simulate_manifest(settings, output):
    cfg = simulation.SimulationConfig.from_dict(settings)
    path = simulation.write_manifest(cfg, Path(output).parent)
    load_manifest(path)  # the simulator must write exactly the raw format


dice_core.run_logged(snakemake.log[0], simulate_manifest, snakemake.params.simulation, snakemake.output.manifest)
