"""Snakemake step: temporal mean and noise maps of the dark acquisition."""

import logging

import dice_core
from dice_core import calibration, io
from dice_core.manifest import load_manifest


def measure_dark(manifest_path, output, config):
    manifest = load_manifest(manifest_path)
    stream = io.FrameStream(manifest.dark, manifest.detector, chunk_frames=config["chunk_frames"],
                            min_frames=2, purpose="a temporal noise map")
    logging.getLogger("dice").info("dark: %d frames in %d file(s)", stream.n_frames, len(stream.cubes))
    maps = calibration.dark_maps(stream, manifest.detector, n_frames=stream.n_frames)
    logging.getLogger("dice").info("dark: median temporal noise %.3f adu", float(maps["noise_median"]))
    io.write_product(maps, output, title=f"dark maps of {manifest.name}", config=config,
                     inputs=[manifest.path, *manifest.dark.files])


dice_core.run_logged(snakemake.log[0], measure_dark, snakemake.input.manifest, snakemake.output.dark,
                     snakemake.params.settings,
                     provenance={"code_version": snakemake.params.code, **snakemake.params.roots})
