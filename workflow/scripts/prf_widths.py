"""Snakemake step: PRF width maps from the metrology products of every baseline (calibration/prf.nc)."""

import logging

import dice_core
from dice_core import io, prf
from dice_core.manifest import load_manifest


def prf_widths(manifest_path, dark_path, metrology_paths, output, config):
    log = logging.getLogger("dice")
    manifest = load_manifest(manifest_path)
    dark = io.read_product(dark_path)
    products = {}
    for path in metrology_paths:
        product = io.read_product(path)
        products[product.attrs["baseline"]] = product
    options = config["prf"]
    family = prf.PrfFamily(order=options["order"], sigma=options["sigma"], half_width=options["half_width"])
    log.info("PRF widths from %d baseline(s) (%s); kernels: orders %g-%g, sigmas %g-%g pixel, half-widths "
             "%g-%g pixel (%d in the grid)", len(products), ", ".join(sorted(products)), *family.order,
             *family.sigma, *family.half_width, len(family.members))
    maps = prf.width_maps(products, gain=manifest.detector.gain, read_noise=dark["noise"].values, shape=family,
                          smooth_degree=config["metrology"]["smooth_degree"],
                          science=manifest.detector.science_mask(), log=log)
    product = prf.prf_dataset(maps)
    for axis in "xy":
        width, error = product[f"width_{axis}"], product[f"error_width_{axis}"]
        log.info("width_%s: mean %.4f, spread %.2e pixel rms, error %.2e pixel rms", axis, float(width.mean()),
                 float(width.std()), float((error**2).mean() ** 0.5))
    io.write_product(product, output, title=f"PRF width maps of {manifest.name}", config=config,
                     inputs=[manifest.path, dark_path, *metrology_paths])


dice_core.run_logged(snakemake.log[0], prf_widths, snakemake.input.manifest, snakemake.input.dark,
                     list(snakemake.input.metrology), snakemake.output.prf, snakemake.params.settings,
                     provenance={"code_version": snakemake.params.code, **snakemake.params.roots})
