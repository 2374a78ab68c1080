"""Snakemake step: x and y pixel offsets from a pair of baselines (appendix A)."""

import logging

import dice_core
from dice_core import deprojection, io


def deproject_offsets(first_path, second_path, pair, baselines, output, config):
    first, second = io.read_product(first_path), io.read_product(second_path)
    offsets = deprojection.offsets_dataset(first, second, label=f"pair {pair} ({' and '.join(baselines)})")
    offsets.attrs.update({"pair": pair, "baselines": " ".join(baselines)})
    logging.getLogger("dice").info("pair %s (%s): dx rms %.3e, dy rms %.3e pixel", pair, " ".join(baselines),
                                   float(offsets["dx_rms"]), float(offsets["dy_rms"]))
    io.write_product(offsets, output, title=f"pixel offsets from pair {pair}", config=config,
                     inputs=[first_path, second_path])


dice_core.run_logged(snakemake.log[0], deproject_offsets, snakemake.input.first, snakemake.input.second,
                     snakemake.wildcards.pair, snakemake.params.baselines, snakemake.output.offsets, snakemake.config,
                     provenance={"code_version": snakemake.params.code, **snakemake.params.roots})
