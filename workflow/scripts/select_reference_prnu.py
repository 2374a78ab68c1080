"""Snakemake step: the reference flat's PRNU becomes calibration/prnu.nc (the stable product)."""

import dice_core
from dice_core import io


def select_reference_prnu(source, reference, output, config):
    prnu = io.read_product(source)
    prnu.attrs = {"flat": reference}
    io.write_product(prnu, output, title=f"reference PRNU (flat {reference})", config=config, inputs=[source])


dice_core.run_logged(snakemake.log[0], select_reference_prnu, snakemake.input.prnu, snakemake.params.reference,
                     snakemake.output.prnu, snakemake.params.settings,
                     provenance={"code_version": snakemake.params.code, **snakemake.params.roots})
