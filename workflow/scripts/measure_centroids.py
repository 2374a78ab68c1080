"""Snakemake step: centroids of the pseudo stars at every detector position, in one calibration mode."""

import logging

import dice_core
from dice_core import centroids, chromatic, io, stacks
from dice_core.manifest import load_manifest


def read_stacks(paths):
    """Each position's stack, read when the centroids reach it: one in memory at a time."""
    for path in paths:
        yield stacks.PositionStack.from_dataset(io.read_product(path))


def measure_centroids(manifest_path, dark_path, prnu_path, offsets_path, bad_pixel_paths, stack_paths, mode, output,
                      settings, method, prf_path=None, chromatic_path=None):
    """``settings``: the step's configuration (centroids.half_size...), which the product records; ``method``:
    the centroid method, the configured one or, for centroids/<method>/<mode>.nc, the path's (the product's
    attribute ``method``)."""
    options = {**settings["centroids"], "method": method}
    log = logging.getLogger("dice")
    manifest = load_manifest(manifest_path)
    use_flat, use_metrology = centroids.mode_corrections(mode)
    use_widths = "widths" in centroids.mode_needs(mode)
    dark = io.read_product(dark_path)
    prnu = io.read_product(prnu_path)["prnu"].values if use_flat else None
    dx = dy = None
    if use_metrology:
        offsets = io.read_product(offsets_path)
        dx, dy = offsets["dx"].values, offsets["dy"].values
    variance_x = variance_y = None
    if use_widths:  # each pixel's PRF variance minus the mean one (NaN where not measured: none)
        widths = io.read_product(prf_path)
        variance_x, variance_y = (widths[f"variance_deviation_{axis}"].values for axis in "xy")
    if "chromatic" in centroids.mode_needs(mode):  # the flat, the offsets and the widths' change the spectrum sees
        spectrum = chromatic.stars_spectrum(options.get("spectrum"), manifest.spectrum)
        found = chromatic.star_calibration(io.read_product(chromatic_path), spectrum, white_prnu=prnu, log=log)
        prnu, dx, dy, variance_x, variance_y = (found[k] for k in ("prnu", "dx", "dy", "variance_x", "variance_y"))
    # dead, hot and column defects are left out or refuse a star; dust pixels are the flat's to correct
    bad_pixels = io.read_product(bad_pixel_paths[0])["bad_pixel"].values if bad_pixel_paths else None
    positions = [p.index for p in manifest.positions]
    log.info("mode %s (flat %s, pixel offsets %s%s), method %s, %d positions, %d stars, %dx%d windows", mode,
             use_flat, use_metrology, ", PRF widths True" if use_widths else "", options["method"], len(positions),
             len(manifest.star_approx),
             2 * options["half_size"] + 1, 2 * options["half_size"] + 1)
    result = centroids.measure_positions(
        read_stacks(stack_paths), positions, approx=manifest.star_approx, detector=manifest.detector,
        dark=dark["dark"].values, read_noise=dark["noise"].values, prnu=prnu, dx=dx, dy=dy, bad_pixels=bad_pixels,
        method=options["method"], half_size=options["half_size"], label=f"mode {mode}", log=log,
        variance_x=variance_x, variance_y=variance_y)
    product = centroids.centroids_dataset(result, positions, mode=mode, method=options["method"])
    inputs = [manifest.path, dark_path, *([prnu_path] if use_flat else []), *([offsets_path] if use_metrology else []),
              *([prf_path] if use_widths else []), *([chromatic_path] if chromatic_path else []),
              *bad_pixel_paths, *stack_paths]
    io.write_product(product, output, title=f"pseudo-star centroids of {manifest.name}, mode {mode}",
                     config=settings, inputs=inputs)


dice_core.run_logged(snakemake.log[0], measure_centroids, snakemake.input.manifest, snakemake.input.dark,
                     snakemake.input.get("prnu"), snakemake.input.get("offsets"),
                     list(snakemake.input.get("bad_pixels", [])), list(snakemake.input.stacks),
                     snakemake.wildcards.mode,
                     snakemake.output.centroids, snakemake.params.settings, snakemake.params.method,
                     snakemake.input.get("prf"), snakemake.input.get("chromatic"),
                     provenance={"code_version": snakemake.params.code, **snakemake.params.roots})
