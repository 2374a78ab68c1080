"""Snakemake step: the coherent stray-light study's figure (issue 25): a pair's offset error, left in and removed."""

import dice_core
from dice_core import io, plotting


def plot_stray_light_study(points, png, pdf):
    plotting.save(plotting.stray_light_study_figure([io.read_product(p) for p in points]), png, pdf=pdf)


dice_core.run_logged(snakemake.log[0], plot_stray_light_study, list(snakemake.input.points), snakemake.output.png,
                     snakemake.output.pdf)
