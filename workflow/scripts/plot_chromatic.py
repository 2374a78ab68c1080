"""Snakemake step: each wavelength's offsets and sensitivity against the reference's (calibration/chromatic.nc)."""

import dice_core
from dice_core import io, plotting
from dice_core.manifest import load_manifest


def plot_chromatic(path, manifest_path, png, pdf):
    detector = load_manifest(manifest_path, check_files=False).detector
    plotting.save(plotting.chromatic_figure(io.read_product(path), detector), png, pdf=pdf)


dice_core.run_logged(snakemake.log[0], plot_chromatic, snakemake.input.chromatic, snakemake.input.manifest,
                     snakemake.output.png, snakemake.output.pdf)
