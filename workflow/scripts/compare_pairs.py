"""Snakemake step: difference between a pair's offsets and the reference pair's (metrology systematics)."""

import logging

import numpy as np
import xarray as xr

import dice_core
from dice_core import deprojection, io


def compare_pairs(reference_path, other_path, reference, pair, output, config):
    ref, other = io.read_product(reference_path), io.read_product(other_path)
    modes = [(p["unobservable_dx"].values, p["unobservable_dy"].values) for p in (ref, other)
             if "unobservable_dx" in p]  # spherical waves: the difference orthogonal to both pairs' modes
    ddx, ddy, sdx, sdy = deprojection.pair_difference(ref["dx"].values, ref["dy"].values,
                                                      other["dx"].values, other["dy"].values, modes=modes)
    floor_dx = np.hypot(ref["dx_photon_noise_floor"].values, other["dx_photon_noise_floor"].values)
    floor_dy = np.hypot(ref["dy_photon_noise_floor"].values, other["dy_photon_noise_floor"].values)
    rc = ("row", "col")
    product = xr.Dataset(
        {
            "ddx": (rc, ddx, {"units": "pixel", "long_name": f"dx({pair}) - dx({reference})"}),
            "ddy": (rc, ddy, {"units": "pixel", "long_name": f"dy({pair}) - dy({reference})"}),
            "ddx_std": ((), sdx, {"units": "pixel", "long_name": "standard deviation of ddx"}),
            "ddy_std": ((), sdy, {"units": "pixel", "long_name": "standard deviation of ddy"}),
            "ddx_photon_noise_floor": ((), float(np.sqrt(np.nanmean(floor_dx**2))),
                                       {"units": "pixel", "long_name": "rms photon-noise floor of ddx"}),
            "ddy_photon_noise_floor": ((), float(np.sqrt(np.nanmean(floor_dy**2))),
                                       {"units": "pixel", "long_name": "rms photon-noise floor of ddy"}),
        },
        coords={"row": ref["row"].values, "col": ref["col"].values},
    )
    product.attrs.update({"reference_pair": reference, "pair": pair})
    logging.getLogger("dice").info("%s - %s: std(ddx) %.3e, std(ddy) %.3e pixel; photon floor %.3e, %.3e",
                                   pair, reference, sdx, sdy, float(product["ddx_photon_noise_floor"]),
                                   float(product["ddy_photon_noise_floor"]))
    io.write_product(product, output, title=f"offset difference {pair} - {reference}", config=config,
                     inputs=[reference_path, other_path])


dice_core.run_logged(snakemake.log[0], compare_pairs, snakemake.input.reference, snakemake.input.other,
                     snakemake.params.reference, snakemake.wildcards.pair, snakemake.output.difference,
                     snakemake.config, provenance={"code_version": snakemake.params.code, **snakemake.params.roots})
