"""Snakemake step of a split fringe fit: the state before pass 1 (reference frame, pass 1's projector)."""

import logging

import dice_core
from dice_core import calibration, fringe_fit, io
from dice_core.manifest import load_manifest


def fit_start(manifest_path, dark_path, prnu_paths, bad_pixel_paths, baseline, output, config):
    log = logging.getLogger("dice")
    manifest = load_manifest(manifest_path)
    dark = io.read_product(dark_path)
    flat, bad_pixels = calibration.fringe_fit_calibrations(prnu_paths, bad_pixel_paths, label=f"baseline {baseline}")
    stream = fringe_fit.metrology_stream(manifest.baselines[baseline], manifest.detector,
                                         chunk_frames=config["chunk_frames"])
    options = config["metrology"]
    log.info("baseline %s: %d frames in %d file(s), fitted in %d part(s) of whole files, at most %d passes; "
             "flat %s", baseline, stream.n_frames, len(stream.cubes), len(stream.split(options["parts"])),
             options["max_passes"], "used for the gauge" if flat is not None else "not used")
    state = fringe_fit.start_fit(stream, dark["dark"].values, detector=manifest.detector, flat=flat,
                                 tolerance=options["tolerance"], max_passes=options["max_passes"],
                                 smooth_degree=options["smooth_degree"], bad_pixels=bad_pixels,
                                 label=f"baseline {baseline}")
    io.write_product(fringe_fit.state_dataset(state), output,
                     title=f"split fringe fit of baseline {baseline} of {manifest.name}: state before pass 1",
                     config=config, inputs=[manifest.path, dark_path, *prnu_paths, *bad_pixel_paths])


dice_core.run_logged(snakemake.log[0], fit_start, snakemake.input.manifest, snakemake.input.dark,
                     list(snakemake.input.prnu), list(snakemake.input.bad_pixels), snakemake.wildcards.baseline,
                     snakemake.output.state, snakemake.params.settings,
                     provenance={"code_version": snakemake.params.code, **snakemake.params.roots})
