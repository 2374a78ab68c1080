"""Snakemake step: Procrustes and barycentre residuals per position, one row per calibration mode."""

import dice_core
from dice_core import io, plotting


def plot_procrustes_residuals(path, png, pdf, barycentre_png, barycentre_pdf):
    residuals = io.read_product(path)
    plotting.save(plotting.procrustes_figure(residuals), png, pdf=pdf)
    plotting.save(plotting.barycentre_figure(residuals), barycentre_png, pdf=barycentre_pdf)


dice_core.run_logged(snakemake.log[0], plot_procrustes_residuals, snakemake.input.residuals, snakemake.output.png,
                     snakemake.output.pdf, snakemake.output.barycentre_png, snakemake.output.barycentre_pdf)
