"""Snakemake step: the figure of the error-propagation coefficients (its own job: a plot edit re-runs no table)."""

import dice_core
from dice_core import io, plotting, studies


def plot_error_propagation(points, png, pdf):
    sweeps = [studies.sweep_from_dataset(io.read_product(p)) for p in points]
    plotting.save(plotting.error_propagation_figure(sweeps), png, pdf=pdf)


dice_core.run_logged(snakemake.log[0], plot_error_propagation, list(snakemake.input.points), snakemake.output.png,
                     snakemake.output.pdf)
