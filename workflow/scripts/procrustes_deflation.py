"""Snakemake step: the Procrustes deflation factor of the paper's geometry by Monte Carlo,
tables/procrustes_deflation.csv (its own job: the comparison's figure never re-runs it)."""

import logging

import dice_core
from dice_core import io, reproduction


def procrustes_deflation(csv_path, trials):
    positions = 33  # the paper's positions 25-57
    factor, error = reproduction.procrustes_deflation(positions, trials=trials)
    logging.getLogger("dice").info("Procrustes deflation factor, 5 stars, %d positions: %.4f +- %.4f (%d trials)",
                                   positions, factor, error, trials)
    io.write_text(csv_path, f"factor,error,trials,positions,stars\n{factor:.6g},{error:.6g},{trials},{positions},5\n")


dice_core.run_logged(snakemake.log[0], procrustes_deflation, snakemake.output.csv,
                     snakemake.params.settings["astrometry"]["trials"])
