"""Snakemake step: x and y pixel offsets from a pair of baselines (appendix A)."""

import logging

import dice_core
from dice_core import DatasetError, deprojection, io


def deproject_offsets(manifest_path, first_path, second_path, pair, baselines, output, config):
    first, second = io.read_product(first_path), io.read_product(second_path)
    try:
        offsets = deprojection.offsets_dataset(first, second,
                                               label=f"metrology.pairs.{pair} ({' and '.join(baselines)})")
    except deprojection.DeprojectionError as exc:  # the manifest's pair is the cause: name it
        raise DatasetError(manifest_path, str(exc)) from None
    offsets.attrs.update({"pair": pair, "baselines": " ".join(baselines)})
    logging.getLogger("dice").info("pair %s (%s): dx rms %.3e, dy rms %.3e pixel", pair, " ".join(baselines),
                                   float(offsets["dx_rms"]), float(offsets["dy_rms"]))
    io.write_product(offsets, output, title=f"pixel offsets from pair {pair}", config=config,
                     inputs=[first_path, second_path])


dice_core.run_logged(snakemake.log[0], deproject_offsets, snakemake.input.manifest, snakemake.input.first,
                     snakemake.input.second,
                     snakemake.wildcards.pair, snakemake.params.baselines, snakemake.output.offsets,
                     snakemake.params.settings,
                     provenance={"code_version": snakemake.params.code, **snakemake.params.roots})
