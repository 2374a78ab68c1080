"""Snakemake step: figure of the difference between two flats' PRNU maps (paper's PRNU-difference figure)."""

import dice_core
from dice_core import io, plotting
from dice_core.manifest import load_manifest


def plot_prnu_difference(diff_path, manifest_path, png, pdf):
    detector = load_manifest(manifest_path, check_files=False).detector
    diff = io.read_product(diff_path)
    title = f"PRNU difference, {diff.attrs['other_flat']} - {diff.attrs['reference_flat']}"
    note = (f"rms {float(diff['difference_rms']):.2e}, photon-noise limit "
            f"{float(diff['photon_noise_limit_rms']):.2e}, relative to the mean response")
    fig = plotting.map_figure(diff["difference"].values, detector, title=title, units="difference [1e-4]",
                              scale=1e4, symmetric=True, note=note)
    plotting.save(fig, png, pdf=pdf)


dice_core.run_logged(snakemake.log[0], plot_prnu_difference, snakemake.input.difference,
                     snakemake.input.manifest, snakemake.output.png, snakemake.output.pdf)
