"""Snakemake step: a baseline's offset spectrum with the stray-light components found, and their phase error."""

import dice_core
from dice_core import io, plotting
from dice_core.manifest import load_manifest


def plot_stray_light(path, manifest_path, baseline, png, pdf):
    detector = load_manifest(manifest_path, check_files=False).detector
    fig = plotting.stray_light_figure(io.read_product(path), detector,
                                      title=f"Coherent stray light, baseline {baseline}")
    plotting.save(fig, png, pdf=pdf)


dice_core.run_logged(snakemake.log[0], plot_stray_light, snakemake.input.stray, snakemake.input.manifest,
                     snakemake.wildcards.baseline, snakemake.output.png, snakemake.output.pdf)
