"""Snakemake step: figures of the mean dark and of the dark temporal noise (paper's dark figures)."""

import dice_core
from dice_core import io, plotting
from dice_core.manifest import load_manifest


def plot_dark(dark_path, manifest_path, out):
    detector = load_manifest(manifest_path, check_files=False).detector
    dark = io.read_product(dark_path)
    n = int(dark["n_frames"])
    fig = plotting.map_figure(dark["dark"].values, detector, title=f"Mean dark frame ({n} frames)", units="adu")
    plotting.save(fig, out.dark_png, pdf=out.dark_pdf)
    noise = dark["noise"].values
    fig = plotting.map_figure(noise, detector, title="Temporal noise of the dark cube", units="adu",
                              note=f"median {float(dark['noise_median']):.3f} adu")
    plotting.save(fig, out.noise_png, pdf=out.noise_pdf)


dice_core.run_logged(snakemake.log[0], plot_dark, snakemake.input.dark, snakemake.input.manifest,
                     snakemake.output)
