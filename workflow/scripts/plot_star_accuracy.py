"""Snakemake step: a star_accuracy sweep's accuracy of each calibration mode against its parameter."""

import json

import dice_core
from dice_core import io, plotting


def plot_star_accuracy(points, sweep, png, pdf):
    datasets = [io.read_product(p) for p in points]
    values = [json.loads(ds.attrs["point"]) for ds in datasets]
    plotting.save(plotting.star_accuracy_figure(datasets, values, title=f"sweep {sweep}"), png, pdf=pdf)


dice_core.run_logged(snakemake.log[0], plot_star_accuracy, list(snakemake.input.points), snakemake.wildcards.sweep,
                     snakemake.output.png, snakemake.output.pdf)
