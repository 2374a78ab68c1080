"""Snakemake step: PRNU map of one flat (the paper's five steps) with its photon-noise limit."""

import logging

import dice_core
from dice_core import calibration, io
from dice_core.manifest import load_manifest


def measure_prnu(manifest_path, dark_path, flat, output, config):
    log = logging.getLogger("dice")
    manifest = load_manifest(manifest_path)
    dark = io.read_product(dark_path)
    stream = io.FrameStream(manifest.flats[flat], manifest.detector, chunk_frames=config["chunk_frames"],
                            min_frames=2, purpose="a PRNU map with its noise")
    log.info("flat %s: %d frames in %d file(s)", flat, stream.n_frames, len(stream.cubes))
    prnu = calibration.prnu_map(stream, dark["dark"].values, dark_noise=dark["noise"].values,
                                detector=manifest.detector, gradient_degree=config["prnu"]["gradient_degree"],
                                n_frames=stream.n_frames, label=f"flat {flat}")
    log.info("flat %s: PRNU rms %.3e, photon-noise limit %.3e", flat, float(prnu["prnu_rms"]),
             float(prnu["photon_noise_limit_rms"]))
    prnu.attrs["flat"] = flat
    io.write_product(prnu, output, title=f"PRNU of flat {flat} of {manifest.name}", config=config,
                     inputs=[manifest.path, dark_path, *manifest.flats[flat].files])


dice_core.run_logged(snakemake.log[0], measure_prnu, snakemake.input.manifest, snakemake.input.dark,
                     snakemake.wildcards.flat, snakemake.output.prnu, snakemake.params.settings,
                     provenance={"code_version": snakemake.params.code, **snakemake.params.roots})
