"""Snakemake step: difference between a pair's offsets and the reference pair's (metrology systematics)."""

import logging

import dice_core
from dice_core import deprojection, io


def compare_pairs(reference_path, other_path, reference, pair, output, config):
    product = deprojection.difference_dataset(io.read_product(reference_path), io.read_product(other_path),
                                              reference_pair=reference, pair=pair,
                                              spectrum=config["metrology"]["stray_light"] != "off")
    logging.getLogger("dice").info("%s - %s: std(ddx) %.3e, std(ddy) %.3e pixel; photon floor %.3e, %.3e",
                                   pair, reference, float(product["ddx_std"]), float(product["ddy_std"]),
                                   float(product["ddx_photon_noise_floor"]),
                                   float(product["ddy_photon_noise_floor"]))
    io.write_product(product, output, title=f"offset difference {pair} - {reference}", config=config,
                     inputs=[reference_path, other_path])


dice_core.run_logged(snakemake.log[0], compare_pairs, snakemake.input.reference, snakemake.input.other,
                     snakemake.params.reference, snakemake.wildcards.pair, snakemake.output.difference,
                     snakemake.params.settings,
                     provenance={"code_version": snakemake.params.code, **snakemake.params.roots})
