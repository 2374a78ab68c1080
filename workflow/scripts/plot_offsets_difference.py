"""Snakemake step: maps of the offset differences between two pairs (paper's offset-difference figures)."""

import dice_core
from dice_core import io, plotting
from dice_core.manifest import load_manifest


def plot_offsets_difference(path, manifest_path, png, pdf):
    detector = load_manifest(manifest_path, check_files=False).detector
    ds = io.read_product(path)
    pair, reference = ds.attrs["pair"], ds.attrs["reference_pair"]
    titles = [f"{axis} difference: std {float(ds[f'd{axis}_std']):.2e} pixel "
              f"(photon floor {float(ds[f'd{axis}_photon_noise_floor']):.1e} pixel)" for axis in ("dx", "dy")]
    fig = plotting.maps_figure([ds["ddx"].values, ds["ddy"].values], detector, scale=1e3,
                               units="difference [1e-3 pixel]", titles=titles,
                               suptitle=f"Pixel offsets, pair {pair} minus pair {reference}")
    plotting.save(fig, png, pdf=pdf)


dice_core.run_logged(snakemake.log[0], plot_offsets_difference, snakemake.input.difference,
                     snakemake.input.manifest, snakemake.output.png, snakemake.output.pdf)
