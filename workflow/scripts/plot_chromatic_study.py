"""Snakemake step: a chromatic sweep's figure, accuracy against the number of calibration wavelengths."""

import dice_core
from dice_core import io, plotting


def plot_chromatic_study(points, png, pdf):
    plotting.save(plotting.chromatic_study_figure([io.read_product(path) for path in points]), png, pdf=pdf)


dice_core.run_logged(snakemake.log[0], plot_chromatic_study, list(snakemake.input.points), snakemake.output.png,
                     snakemake.output.pdf)
