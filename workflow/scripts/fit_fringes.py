"""Snakemake step: global fringe solution of one metrology baseline."""

import logging

import dice_core
from dice_core import DatasetError, calibration, fringe_fit, fringes, io
from dice_core.geometry import BaselineGeometry, GeometryError
from dice_core.manifest import load_manifest


def fit_fringes(manifest_path, dark_path, prnu_paths, bad_pixel_paths, baseline, output, config, workers):
    log = logging.getLogger("dice")
    manifest = load_manifest(manifest_path)
    dark = io.read_product(dark_path)
    flat, bad_pixels = calibration.fringe_fit_calibrations(prnu_paths, bad_pixel_paths, label=f"baseline {baseline}")
    stream = fringe_fit.metrology_stream(manifest.baselines[baseline], manifest.detector,
                                         chunk_frames=config["chunk_frames"])
    options = config["metrology"]
    geometry = None if manifest.geometry is None else BaselineGeometry.of_baseline(
        manifest.geometry, baseline, tip_sigma=options["tip_sigma"],
        wavelength=manifest.baseline_wavelength(baseline))  # format 1.2: the baseline's own laser
    log.info("baseline %s: %d frames in %d file(s); flat %s; %s", baseline, stream.n_frames, len(stream.cubes),
             "used for the gauge" if flat is not None else "not used",
             "plane waves" if geometry is None else
             f"spherical waves of fibers {' and '.join(geometry.fibers)}, nominal tips known to "
             f"{geometry.tip_sigma * 1e3:g} mm")
    try:
        solution = fringe_fit.fit_baseline(stream, dark["dark"].values, detector=manifest.detector, flat=flat,
                                           read_noise=dark["noise"].values, tolerance=options["tolerance"],
                                           max_passes=options["max_passes"], smooth_degree=options["smooth_degree"],
                                           workers=workers, parts=options["parts"], geometry=geometry,
                                           bad_pixels=bad_pixels, label=f"baseline {baseline}")
    except GeometryError as exc:  # the bench the manifest describes does not fit the fringes: name it
        raise DatasetError(manifest.path, f"metrology.geometry: {exc}") from exc
    product = fringes.metrology_product(solution, manifest.detector, baseline=baseline, geometry=geometry)
    io.write_product(product, output, title=f"fringe solution of baseline {baseline} of {manifest.name}",
                     config=config, inputs=[manifest.path, dark_path, *prnu_paths, *bad_pixel_paths,
                                            *manifest.baselines[baseline].files])


dice_core.run_logged(snakemake.log[0], fit_fringes, snakemake.input.manifest, snakemake.input.dark,
                     list(snakemake.input.prnu), list(snakemake.input.bad_pixels), snakemake.wildcards.baseline,
                     snakemake.output.metrology,
                     snakemake.params.settings, snakemake.threads,
                     provenance={"code_version": snakemake.params.code, **snakemake.params.roots})
