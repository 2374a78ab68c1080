"""Snakemake step: the paper's pixel-offset-bias figure, the paper's method beside ours at each PRNU level."""

import dice_core
from dice_core import io, plotting


def plot_offset_bias(points, png, pdf):
    datasets = sorted((io.read_product(p) for p in points), key=lambda ds: ds.attrs["prnu_rms"])
    plotting.save(plotting.offset_bias_figure(datasets), png, pdf=pdf)


dice_core.run_logged(snakemake.log[0], plot_offset_bias, list(snakemake.input.points), snakemake.output.png,
                     snakemake.output.pdf)
