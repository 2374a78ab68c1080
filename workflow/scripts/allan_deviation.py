"""Snakemake step: Allan deviations of one baseline's projected offsets (one more pass over its frames)."""

import logging
from pathlib import Path

import dice_core
from dice_core import allan, io
from dice_core.manifest import load_manifest


def allan_deviation(manifest_path, metrology_path, dark_path, baseline, output, config, workers):
    log = logging.getLogger("dice")
    manifest = load_manifest(manifest_path)
    # the fit hashed these files as it read them: their SHA-256 taken from the results' store, not hashed again
    # (1.5 s of 6.6 on a paper baseline: cProfile of the step's calls in one process, not the workflow's run);
    # a file that is not the version the fit hashed is hashed as it is read
    files = manifest.baselines[baseline].files
    adopted = io.adopt_stored_digests(files)
    log.info("baseline %s: the SHA-256 of %d of its %d file(s) taken from the fit's, as it hashed them", baseline,
             len(adopted), len(files))
    stream = io.FrameStream(manifest.baselines[baseline], manifest.detector, chunk_frames=config["chunk_frames"],
                            purpose="Allan deviations", dtype="float32")
    # the products opened lazily: the step reads the maps it needs, at its pixels (not the whole solution);
    # what grows with pixels times batches goes to a scratch folder beside the product (the results' disk)
    with io.open_product(metrology_path) as metrology, io.open_product(dark_path) as dark:
        product = allan.allan_of_baseline(stream, metrology, dark=dark, detector=manifest.detector,
                                          workers=workers, label=f"baseline {baseline}",
                                          scratch=Path(output).parent)
    last = product.isel(n_frames=-1)
    log.info("baseline %s: slope %.3f; at %.0f frames per group, %.2e pixel (photon limit %.2e) for pixels, "
             "%.2e (limit %.2e) for blocks", baseline, float(product["slope"]), float(last["n_frames"]),
             float(last["deviation_mean"]), float(last["photon_limit_pixel"]), float(last["deviation_block_mean"]),
             float(last["photon_limit_block"]))
    product.attrs["baseline"] = baseline
    io.write_product(product, output, title=f"Allan deviations of baseline {baseline} of {manifest.name}",
                     config=config, inputs=[manifest.path, metrology_path, dark_path,
                                            *manifest.baselines[baseline].files])


dice_core.run_logged(snakemake.log[0], allan_deviation, snakemake.input.manifest, snakemake.input.metrology,
                     snakemake.input.dark, snakemake.wildcards.baseline, snakemake.output.allan,
                     snakemake.params.settings,
                     snakemake.threads, provenance={"code_version": snakemake.params.code, **snakemake.params.roots})
