"""Snakemake step: one star position's frames read once into their mean and batch means."""

import logging

import dice_core
from dice_core import io, stacks
from dice_core.manifest import load_manifest


def stack_position(manifest_path, position, output, config, n_batches):
    log = logging.getLogger("dice")
    manifest = load_manifest(manifest_path)
    acquisition = next(p for p in manifest.positions if str(p.index) == position).acquisition
    stream = io.FrameStream(acquisition, manifest.detector, chunk_frames=config["chunk_frames"], min_frames=n_batches,
                            purpose=f"{n_batches} batches of a position")
    stack = stacks.stack_position(stream, stream.n_frames, n_batches=n_batches, position=int(position),
                                  label=f"position {position}")
    log.info("position %s: %d frames in %d batches; %d saturated sample(s)", position, stack.n_frames, n_batches,
             int(stack.n_saturated.sum()))
    io.write_product(stack.to_dataset(), output,
                     title=f"mean and batch means of star position {position} of {manifest.name}",
                     config=config, inputs=[manifest.path, *acquisition.files])


dice_core.run_logged(snakemake.log[0], stack_position, snakemake.input.manifest, snakemake.wildcards.position,
                     snakemake.output.stack,
                     snakemake.params.settings, snakemake.params.settings["centroids"]["batches"],
                     provenance={"code_version": snakemake.params.code, **snakemake.params.roots})
