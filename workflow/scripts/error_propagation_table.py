"""Snakemake step: the paper's error-propagation coefficients, tables/error_propagation.csv (its figure: plot_error_propagation)."""

import logging

import dice_core
from dice_core import error_budget, io, studies


def error_propagation_table(points, csv_path):
    log = logging.getLogger("dice")
    sweeps = [studies.sweep_from_dataset(io.read_product(p)) for p in points]
    rows = error_budget.combined_table(sweeps)
    for row in rows:
        log.info("%-8s pipeline fit: per axis %.4f +- %.4f (analytic %.4f), 2-D %.4f, paper %.2f: %s", row["source"],
                 row["coefficient"], row["error"], row["analytic"], row["coefficient_2d"], row["paper_coefficient"],
                 row["convention_matching_paper"])
        if "coefficient_uniform" in row:
            log.info("%-8s unweighted fit: per axis %.4f +- %.4f (analytic %.4f), 2-D %.4f: %s", row["source"],
                     row["coefficient_uniform"], row["error_uniform"], row["analytic_uniform"],
                     row["coefficient_2d_uniform"], row["convention_matching_paper_uniform"])
    io.write_text(csv_path, error_budget.error_propagation_csv(rows))


dice_core.run_logged(snakemake.log[0], error_propagation_table, list(snakemake.input.points), snakemake.output.csv)
