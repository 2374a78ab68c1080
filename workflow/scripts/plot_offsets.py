"""Snakemake step: maps of the x and y pixel offsets of one pair (paper's offset figures)."""

import dice_core
from dice_core import io, plotting
from dice_core.manifest import load_manifest


def plot_offsets(path, manifest_path, pair, png, pdf):
    detector = load_manifest(manifest_path, check_files=False).detector
    ds = io.read_product(path)
    fig = plotting.maps_figure(
        [ds["dx"].values, ds["dy"].values], detector, scale=1e3, units="offset [1e-3 pixel]",
        titles=[f"horizontal offsets dx, rms {float(ds['dx_rms']):.2e} pixel",
                f"vertical offsets dy, rms {float(ds['dy_rms']):.2e} pixel"],
        suptitle=f"Pixel offsets, pair {pair} ({ds.attrs['baselines']})")
    plotting.save(fig, png, pdf=pdf)


dice_core.run_logged(snakemake.log[0], plot_offsets, snakemake.input.offsets, snakemake.input.manifest,
                     snakemake.wildcards.pair, snakemake.output.png, snakemake.output.pdf)
