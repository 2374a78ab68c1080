"""Snakemake step: the bad-pixel mask (dead, hot, dust, columns) from the dark and the reference PRNU."""

import logging

import dice_core
from dice_core import calibration, io
from dice_core.manifest import load_manifest


def find_bad_pixels(manifest_path, dark_path, prnu_path, output, config):
    log = logging.getLogger("dice")
    manifest = load_manifest(manifest_path)
    mask = calibration.bad_pixel_mask(io.read_product(dark_path), io.read_product(prnu_path)["prnu"].values,
                                      detector=manifest.detector)
    log.info("bad pixels: %s; columns %s", ", ".join(f"{int(mask[f'n_{kind}'])} {kind}"
                                                     for kind in calibration.BAD_PIXEL_FLAGS),
             mask["bad_columns"].values.tolist() or "none")
    io.write_product(mask, output, title=f"bad-pixel mask of {manifest.name}", config=config,
                     inputs=[manifest.path, dark_path, prnu_path])


dice_core.run_logged(snakemake.log[0], find_bad_pixels, snakemake.input.manifest, snakemake.input.dark,
                     snakemake.input.prnu, snakemake.output.bad_pixels, snakemake.params.settings,
                     provenance={"code_version": snakemake.params.code, **snakemake.params.roots})
