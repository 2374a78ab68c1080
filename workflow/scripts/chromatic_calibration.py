"""Snakemake step: every wavelength's calibration gathered across wavelength (calibration/chromatic.nc)."""

import logging

import dice_core
from dice_core import chromatic, io, prf, products
from dice_core.manifest import load_manifest


def by_name(paths, wildcard):
    """Each product path under the name its path gives it (``pair``, ``baseline`` or ``flat``)."""
    return {products.match(path)[1][wildcard]: path for path in paths}


def chromatic_calibration(manifest_path, dark_path, offset_paths, metrology_paths, flat_paths, output, config):
    log = logging.getLogger("dice")
    manifest = load_manifest(manifest_path)
    dark = io.read_product(dark_path)
    options = config["prf"]
    family = prf.PrfFamily(order=options["order"], sigma=options["sigma"], half_width=options["half_width"])
    log.info("%d wavelengths: %s nm", len(manifest.wavelengths),
             ", ".join(f"{w * 1e9:g}" for w in manifest.wavelengths))
    product = chromatic.calibration_from_products(
        manifest, offsets=by_name(offset_paths, "pair"), metrology=by_name(metrology_paths, "baseline"),
        flats=by_name(flat_paths, "flat"), read=io.read_product, gain=manifest.detector.gain,
        read_noise=dark["noise"].values, shape=family, smooth_degree=config["metrology"]["smooth_degree"], log=log)
    io.write_product(product, output, title=f"calibration across wavelength of {manifest.name}", config=config,
                     inputs=[manifest.path, dark_path, *offset_paths, *metrology_paths, *flat_paths])


dice_core.run_logged(snakemake.log[0], chromatic_calibration, snakemake.input.manifest, snakemake.input.dark,
                     list(snakemake.input.offsets), list(snakemake.input.metrology), list(snakemake.input.flats),
                     snakemake.output.chromatic, snakemake.params.settings,
                     provenance={"code_version": snakemake.params.code, **snakemake.params.roots})
