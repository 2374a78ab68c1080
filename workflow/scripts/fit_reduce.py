"""Snakemake step of a split fringe fit: one pass's parts summed in part order, the state after the pass."""

import dice_core
from dice_core import fringe_fit, io


def fit_reduce(state_path, part_paths, baseline, output, config):
    state = io.read_product(state_path)
    options = config["metrology"]
    fringe_fit.check_state_options(state, tolerance=options["tolerance"], max_passes=options["max_passes"],
                                   smooth_degree=options["smooth_degree"])
    product = fringe_fit.reduce_dataset(state, list(part_paths))
    io.write_product(product, output, title=f"split fringe fit of baseline {baseline}: state after pass "
                                            f"{product.attrs['fit_n_pass']}",
                     config=config, inputs=[state_path, *part_paths])


dice_core.run_logged(snakemake.log[0], fit_reduce, snakemake.input.state, list(snakemake.input.parts),
                     snakemake.wildcards.baseline, snakemake.output.state, snakemake.params.settings,
                     provenance={"code_version": snakemake.params.code, **snakemake.params.roots})
