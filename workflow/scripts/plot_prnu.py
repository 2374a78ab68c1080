"""Snakemake step: figure of one flat's PRNU map (paper's PRNU figure)."""

import dice_core
from dice_core import io, plotting
from dice_core.manifest import load_manifest


def plot_prnu(prnu_path, manifest_path, flat, png, pdf):
    detector = load_manifest(manifest_path, check_files=False).detector
    prnu = io.read_product(prnu_path)
    note = (f"rms {float(prnu['prnu_rms']):.2e}, photon-noise limit "
            f"{float(prnu['photon_noise_limit_rms']):.1e}, relative to the mean response ({int(prnu['n_frames'])} "
            "frames)")
    fig = plotting.map_figure((prnu["prnu"].values - 1), detector, title=f"PRNU, flat {flat}",
                              units="PRNU - 1 [1e-3]", scale=1e3, symmetric=True, note=note)
    plotting.save(fig, png, pdf=pdf)


dice_core.run_logged(snakemake.log[0], plot_prnu, snakemake.input.prnu, snakemake.input.manifest,
                     snakemake.wildcards.flat, snakemake.output.png, snakemake.output.pdf)
