"""Snakemake step: the paper's Allan-deviation figure for one baseline."""

import dice_core
from dice_core import io, plotting


def plot_allan(path, baseline, png, pdf):
    fig = plotting.allan_figure(io.read_product(path), title=f"Allan deviations of projected offsets, "
                                                            f"baseline {baseline}")
    plotting.save(fig, png, pdf=pdf)


dice_core.run_logged(snakemake.log[0], plot_allan, snakemake.input.allan, snakemake.wildcards.baseline,
                     snakemake.output.png, snakemake.output.pdf)
