"""Snakemake step: Procrustes residuals per position, one panel per calibration mode."""

import dice_core
from dice_core import io, plotting


def plot_procrustes_residuals(path, png, pdf):
    plotting.save(plotting.procrustes_figure(io.read_product(path)), png, pdf)


dice_core.run_logged(snakemake.log[0], plot_procrustes_residuals, snakemake.input.residuals, snakemake.output.png,
                     snakemake.output.pdf)
