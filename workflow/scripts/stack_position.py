"""Snakemake step: a group of star positions, each position's frames read once into their mean and batch means."""

import logging

import dice_core
from dice_core import io, stacks
from dice_core.manifest import load_manifest


def stack_positions(manifest_path, positions, outputs, config, n_batches):
    """Stack each of ``positions`` (indices) into its ``outputs`` path (in the same order), one after the other."""
    log = logging.getLogger("dice")
    manifest = load_manifest(manifest_path)
    by_index = {p.index: p for p in manifest.positions}
    for done, (index, output) in enumerate(zip(positions, outputs, strict=True)):
        acquisition = by_index[index].acquisition
        stream = io.FrameStream(acquisition, manifest.detector, chunk_frames=config["chunk_frames"],
                                min_frames=n_batches, purpose=f"{n_batches} batches of a position")
        stack = stacks.stack_position(stream, stream.n_frames, n_batches=n_batches, position=index,
                                      label=f"position {index}")
        log.info("position %s (%d of %d): %d frames in %d batches; %d saturated sample(s)", index, done + 1,
                 len(positions), stack.n_frames, n_batches, int(stack.n_saturated.sum()))
        io.write_product(stack.to_dataset(), output,
                         title=f"mean and batch means of star position {index} of {manifest.name}",
                         config=config, inputs=[manifest.path, *acquisition.files])


dice_core.run_logged(snakemake.log[0], stack_positions, snakemake.input.manifest, snakemake.params.positions,
                     list(snakemake.output.stacks),
                     snakemake.params.settings, snakemake.params.settings["centroids"]["batches"],
                     provenance={"code_version": snakemake.params.code, **snakemake.params.roots})
