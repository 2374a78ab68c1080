"""Snakemake step: a superimposition's residuals per position (projective or pose), one row per mode."""

import dice_core
from dice_core import io, plotting

TITLES = {"projective": "Projective residuals (a homography per position)",
          "pose": "Pose residuals (the detector's 3-D pose per position)"}


def plot_superimposition_residuals(path, model, png, pdf):
    residuals = io.read_product(path)
    plotting.save(plotting.procrustes_figure(residuals, title=TITLES[model]), png, pdf=pdf)


dice_core.run_logged(snakemake.log[0], plot_superimposition_residuals, snakemake.input.residuals,
                     snakemake.wildcards.model, snakemake.output.png, snakemake.output.pdf)
