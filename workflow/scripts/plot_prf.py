"""Snakemake step: maps of the PRF widths along x and y and their errors (calibration/prf.nc)."""

import dice_core
from dice_core import io, plotting
from dice_core.manifest import load_manifest


def plot_prf(path, manifest_path, png, pdf):
    detector = load_manifest(manifest_path, check_files=False).detector
    fig = plotting.prf_widths_figure(io.read_product(path), detector)
    plotting.save(fig, png, pdf=pdf)


dice_core.run_logged(snakemake.log[0], plot_prf, snakemake.input.prf, snakemake.input.manifest,
                     snakemake.output.png, snakemake.output.pdf)
