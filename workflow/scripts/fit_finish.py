"""Snakemake step of a split fringe fit: the metrology product from the state after the last pass."""

import dice_core
from dice_core import DatasetError, fringe_fit, fringes, io
from dice_core.geometry import BaselineGeometry, GeometryError
from dice_core.manifest import load_manifest


def fit_finish(manifest_path, dark_path, prnu_paths, bad_pixel_paths, state_path, first_paths, baseline, output,
               config):
    manifest = load_manifest(manifest_path)
    read_noise = io.read_product(dark_path)["noise"].values  # the dark's other maps are not held beside the fit
    options = config["metrology"]
    geometry = None if manifest.geometry is None else BaselineGeometry.of_baseline(
        manifest.geometry, baseline, tip_sigma=options["tip_sigma"],
        wavelength=manifest.baseline_wavelength(baseline))  # format 1.2: the baseline's own laser
    state_product = io.read_product(state_path)
    fringe_fit.check_state_options(state_product, tolerance=options["tolerance"],
                                   max_passes=options["max_passes"], smooth_degree=options["smooth_degree"])
    state = fringe_fit.state_from_dataset(state_product)
    del state_product  # the state holds its arrays: finish_fit frees what it has used only if no dataset holds them
    try:
        solution = fringe_fit.finish_fit(state, detector=manifest.detector, read_noise=read_noise, geometry=geometry)
    except GeometryError as exc:  # the bench the manifest describes does not fit the fringes: name it
        raise DatasetError(manifest.path, f"metrology.geometry: {exc}") from exc
    del state, read_noise  # the solution holds what the product needs
    product = fringes.metrology_product(solution, manifest.detector, baseline=baseline, geometry=geometry)
    # the single fit's inputs, so that the product is the same whichever way it was made; the cubes' checksums
    # as pass 1's parts recorded them while this job reads none of the cubes
    digests = {key: value for path in first_paths for key, value in io.input_digests(path).items()}
    io.write_product(product, output, title=f"fringe solution of baseline {baseline} of {manifest.name}",
                     config=config, digests=digests, inputs=[manifest.path, dark_path, *prnu_paths,
                                                             *bad_pixel_paths, *manifest.baselines[baseline].files])


dice_core.run_logged(snakemake.log[0], fit_finish, snakemake.input.manifest, snakemake.input.dark,
                     list(snakemake.input.prnu), list(snakemake.input.bad_pixels), snakemake.input.state,
                     list(snakemake.input.first), snakemake.wildcards.baseline, snakemake.output.metrology,
                     snakemake.params.settings,
                     provenance={"code_version": snakemake.params.code, **snakemake.params.roots})
