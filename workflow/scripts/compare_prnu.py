"""Snakemake step: difference between a flat's PRNU and the reference PRNU, with its photon-noise limit."""

import logging

import dice_core
from dice_core import calibration, io
from dice_core.manifest import load_manifest


def compare_prnu(reference_path, other_path, manifest_path, output, config):
    manifest = load_manifest(manifest_path, check_files=False)
    reference, other = io.read_product(reference_path), io.read_product(other_path)
    diff = calibration.prnu_difference(reference, other, detector=manifest.detector)
    diff.attrs = {"reference_flat": reference.attrs["flat"], "other_flat": other.attrs["flat"]}
    logging.getLogger("dice").info("PRNU difference %s - %s: rms %.3e, photon-noise limit %.3e",
                                   other.attrs["flat"], reference.attrs["flat"],
                                   float(diff["difference_rms"]), float(diff["photon_noise_limit_rms"]))
    io.write_product(diff, output, title=f"PRNU difference of {manifest.name}", config=config,
                     inputs=[reference_path, other_path])


dice_core.run_logged(snakemake.log[0], compare_prnu, snakemake.input.reference, snakemake.input.other,
                     snakemake.input.manifest, snakemake.output.difference, snakemake.params.settings,
                     provenance={"code_version": snakemake.params.code, **snakemake.params.roots})
