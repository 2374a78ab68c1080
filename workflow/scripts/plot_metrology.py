"""Snakemake step: summary figure of one baseline's fringe solution."""

import dice_core
from dice_core import io, plotting
from dice_core.manifest import load_manifest


def plot_metrology(path, manifest_path, baseline, png, pdf):
    detector = load_manifest(manifest_path, check_files=False).detector
    fig = plotting.metrology_figure(io.read_product(path), detector, title=f"Metrology, baseline {baseline}")
    plotting.save(fig, png, pdf=pdf)


dice_core.run_logged(snakemake.log[0], plot_metrology, snakemake.input.metrology, snakemake.input.manifest,
                     snakemake.wildcards.baseline, snakemake.output.png, snakemake.output.pdf)
