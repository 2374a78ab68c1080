"""Snakemake step: a tip_tilt sweep's accuracies per superimposition and the pose's identifiability."""

import dice_core
from dice_core import io, plotting


def plot_tip_tilt(points, png, pdf):
    plotting.save(plotting.tip_tilt_sweep_figure([io.read_product(p) for p in points]), png, pdf=pdf)


dice_core.run_logged(snakemake.log[0], plot_tip_tilt, list(snakemake.input.points), snakemake.output.png,
                     snakemake.output.pdf)
