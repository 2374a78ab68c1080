"""Snakemake step: Procrustes accuracies of every centroid mode, as tables/accuracy.csv and a LaTeX table."""

import logging

import dice_core
from dice_core import astrometry, io


def accuracy_table(centroid_paths, csv_path, tex_path, residuals_path, config):
    log = logging.getLogger("dice")
    options = config["astrometry"]
    by_method = {}
    for path in centroid_paths:
        ds = io.read_product(path)
        by_method.setdefault(ds.attrs["method"], {})[ds.attrs["mode"]] = ds
    primary = config["centroids"]["method"]  # its products are centroids/<mode>.nc, which the figures show
    methods = [m for m in [primary, *config["centroids"]["methods"]] if m in by_method]
    methods = list(dict.fromkeys(methods))
    rows, tables = [], []
    for method in methods:
        method_rows, method_residuals = astrometry.mode_accuracies(
            by_method[method], positions=options["positions"], groups=options["groups"], trials=options["trials"])
        rows += method_rows
        tables.append(f"% centroid method: {method}\n" + astrometry.latex_table(method_rows))
        if method == methods[0]:  # centroids.method's, the products centroids/<mode>.nc
            first_datasets, first_rows, first_residuals = by_method[method], method_rows, method_residuals
    for row in rows:
        log.info("%-8s mode %-15s %-8s n=%-3d accuracy %.2e +- %.1e pixel (rms residual %.2e x factor %.3f)",
                 row["method"], row["mode"], row["grouping"], row["n"], row["accuracy"], row["error"],
                 row["rms_residual"], row["factor"])
    io.write_text(csv_path, astrometry.accuracy_csv(rows))
    io.write_text(tex_path, "\n".join(tables))
    product = astrometry.residuals_dataset(first_datasets, first_rows, first_residuals)
    io.write_product(product, residuals_path, title="Procrustes residuals per calibration mode", config=config,
                     inputs=list(centroid_paths))


dice_core.run_logged(snakemake.log[0], accuracy_table, list(snakemake.input.centroids), snakemake.output.csv,
                     snakemake.output.tex, snakemake.output.residuals, snakemake.config)
