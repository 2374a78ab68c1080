"""Snakemake step: a baseline's offset spectrum and the coherent stray light it shows (docs/metrology.md)."""

import dice_core
from dice_core import io, stray_light


def find_stray_light(metrology_path, baseline, output, config):
    product = stray_light.stray_light_dataset(io.read_product(metrology_path), baseline=baseline)
    io.write_product(product, output, title=f"coherent stray light in baseline {baseline}", config=config,
                     inputs=[metrology_path])


dice_core.run_logged(snakemake.log[0], find_stray_light, snakemake.input.metrology, snakemake.wildcards.baseline,
                     snakemake.output.stray, snakemake.params.settings,
                     provenance={"code_version": snakemake.params.code, **snakemake.params.roots})
