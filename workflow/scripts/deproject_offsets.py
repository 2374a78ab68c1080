"""Snakemake step: x and y pixel offsets from a pair of baselines (appendix A)."""

import logging

import dice_core
from dice_core import DatasetError, deprojection, io


def deproject_offsets(manifest_path, first_path, second_path, stray_paths, pair, baselines, output, config):
    first, second = io.read_product(first_path), io.read_product(second_path)
    # metrology.stray_light: remove gives the two baselines' stray-light products, whose components go
    stray = [io.read_product(path) for path in stray_paths] if stray_paths else [None, None]
    try:
        offsets = deprojection.offsets_dataset(first, second, stray=stray,
                                               label=f"metrology.pairs.{pair} ({' and '.join(baselines)})")
    except deprojection.DeprojectionError as exc:  # the manifest's pair is the cause: name it
        raise DatasetError(manifest_path, str(exc)) from None
    offsets.attrs.update({"pair": pair, "baselines": " ".join(baselines)})
    removed = sum(int(s["n_components"]) for s in stray if s is not None)
    logging.getLogger("dice").info("pair %s (%s): dx rms %.3e, dy rms %.3e pixel%s", pair, " ".join(baselines),
                                   float(offsets["dx_rms"]), float(offsets["dy_rms"]),
                                   f"; {removed} stray-light component(s) removed" if stray_paths else "")
    io.write_product(offsets, output, title=f"pixel offsets from pair {pair}", config=config,
                     inputs=[first_path, second_path, *stray_paths])


dice_core.run_logged(snakemake.log[0], deproject_offsets, snakemake.input.manifest, snakemake.input.first,
                     snakemake.input.second, list(snakemake.input.stray),
                     snakemake.wildcards.pair, snakemake.params.baselines, snakemake.output.offsets,
                     snakemake.params.settings,
                     provenance={"code_version": snakemake.params.code, **snakemake.params.roots})
