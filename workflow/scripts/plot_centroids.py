"""Snakemake step: star windows and the central star's path over the positions, for one mode."""

import dice_core
from dice_core import io, plotting


def plot_centroids(path, mode, png, pdf, positions=None):
    """``positions``: the inclusive index range used for the accuracies (config astrometry.positions), in red."""
    fig = plotting.centroids_figure(io.read_product(path), title=f"Pseudo stars, mode {mode}", positions=positions)
    plotting.save(fig, png, pdf=pdf)


dice_core.run_logged(snakemake.log[0], plot_centroids, snakemake.input.centroids, snakemake.wildcards.mode,
                     snakemake.output.png, snakemake.output.pdf,
                     snakemake.params.settings["astrometry"]["positions"])
