"""Snakemake step of a split fringe fit: one part's (group of files') share of one pass."""

import logging

import xarray as xr

import dice_core
from dice_core import fringe_fit, io
from dice_core.manifest import load_manifest


def fit_part(manifest_path, state_path, baseline, part, output, config):
    manifest = load_manifest(manifest_path)
    stream = fringe_fit.metrology_stream(manifest.baselines[baseline], manifest.detector,
                                         chunk_frames=config["chunk_frames"])
    parts = config["metrology"]["parts"]
    # the part's files as an earlier pass hashed them (the results' store), not hashed again as this pass reads
    mine = [cube.path for piece in stream.split(parts)[part:part + 1] for cube in piece.cubes]
    logging.getLogger("dice").info("the SHA-256 of %d of the part's %d file(s) taken from an earlier read",
                                   len(io.adopt_stored_digests(mine)), len(mine))
    with xr.open_dataset(state_path, engine="netcdf4") as state:  # read lazily: the projector only
        fringe_fit.check_state_options(state, tolerance=config["metrology"]["tolerance"],
                                       max_passes=config["metrology"]["max_passes"],
                                       smooth_degree=config["metrology"]["smooth_degree"])
        product = fringe_fit.part_dataset(stream, state, part=part, parts=parts)
    # the files' checksums: adopted above, or taken as the pass read them (a part that read nothing records none)
    files = [] if product.attrs["fit_empty"] else mine
    io.write_product(product, output, title=f"split fringe fit of baseline {baseline} of {manifest.name}: pass "
                                            f"{product.attrs['fit_pass']}, part {part}",
                     config=config, inputs=[state_path, *files])


dice_core.run_logged(snakemake.log[0], fit_part, snakemake.input.manifest, snakemake.input.state,
                     snakemake.wildcards.baseline, int(snakemake.wildcards.part),
                     snakemake.output.part, snakemake.params.settings,
                     provenance={"code_version": snakemake.params.code, **snakemake.params.roots})
