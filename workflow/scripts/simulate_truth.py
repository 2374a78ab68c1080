"""Snakemake step: the simulated testbed's truth (detector model and per-frame parameters)."""

import dice_core
from dice_core import simulation
from dice_core.io import write_product


def simulate_truth(settings, output):
    cfg = simulation.SimulationConfig.from_dict(settings)
    truth = simulation.make_truth(cfg)
    write_product(truth, output, title=f"truth of simulated dataset {cfg.name}", config=settings)


dice_core.run_logged(snakemake.log[0], simulate_truth, snakemake.params.simulation, snakemake.output.truth,
                     provenance={"code_version": snakemake.params.code})
