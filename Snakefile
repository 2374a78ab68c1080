"""DICE detector-calibration workflow.

    snakemake --cores 2                                    # simulate and reduce the built-in dataset
    snakemake --cores 2 --config dataset=PATH/dataset.yaml # reduce a dataset in the raw format
    snakemake --cores 2 paper                              # and regenerate the paper's simulations beside it

Stages are one rule file each under workflow/rules/; the numerics are in dice_core.
"""

from pathlib import Path

from snakemake.utils import min_version

min_version("9.0")


configfile: str(Path(workflow.basedir) / "config" / "config.yaml")


include: "workflow/rules/locks.smk"
include: "workflow/rules/common.smk"
include: "workflow/rules/simulate.smk"
include: "workflow/rules/calibration.smk"
include: "workflow/rules/metrology.smk"
include: "workflow/rules/centroids.smk"
include: "workflow/rules/astrometry.smk"
include: "workflow/rules/figures.smk"
include: "workflow/rules/paper.smk"
include: "workflow/rules/preflight.smk"


rule all:
    default_target: True
    input:
        DEFAULT_TARGETS,
