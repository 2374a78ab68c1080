"""Snakemake step: Procrustes accuracies of every centroid mode, as tables/accuracy.csv and a LaTeX table."""

import csv
import logging
import os
import tempfile
from pathlib import Path

import numpy as np
import xarray as xr

import dice_core
from dice_core import astrometry, io

COLUMNS = ["flat", "metrology", "grouping", "accuracy", "error", "mode", "method", "n", "rms_residual", "factor"]


def write_text_atomically(path, text):
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
    with os.fdopen(fd, "w", newline="") as f:
        f.write(text)
    os.replace(tmp, path)


def _barycentre(configurations):
    """Barycentre residuals over the positions where every star was measured (NaN elsewhere)."""
    complete = np.isfinite(configurations).all(axis=(1, 2))
    out = np.full(configurations.shape, np.nan)
    if complete.sum() >= 2:
        out[complete] = astrometry.barycentre_residuals(configurations[complete])
    return out


def accuracy_table(centroid_paths, csv_path, tex_path, residuals_path, config):
    log = logging.getLogger("dice")
    options = config["astrometry"]
    by_method = {}
    for path in centroid_paths:
        ds = io.read_product(path)
        by_method.setdefault(ds.attrs["method"], {})[ds.attrs["mode"]] = ds
    methods = [m for m in config["centroids"]["methods"] if m in by_method]
    rows, tables = [], []
    for method in methods:
        method_rows, method_residuals = astrometry.mode_accuracies(
            by_method[method], positions=options["positions"], groups=options["groups"], trials=options["trials"])
        rows += method_rows
        tables.append(f"% centroid method: {method}\n" + astrometry.latex_table(method_rows))
        if method == methods[0]:  # the figures show the first method, whose products are centroids/<mode>.nc
            datasets, residuals = by_method[method], method_residuals
    for row in rows:
        log.info("%-8s mode %-15s %-8s n=%-3d accuracy %.2e +- %.1e pixel (rms residual %.2e x factor %.3f)",
                 row["method"], row["mode"], row["grouping"], row["n"], row["accuracy"], row["error"],
                 row["rms_residual"], row["factor"])
    lines = [",".join(COLUMNS)]
    for row in rows:
        lines.append(",".join(f"{row[c]:.6e}" if isinstance(row[c], float) else str(row[c]).lower()
                              if isinstance(row[c], bool) else str(row[c]) for c in COLUMNS))
    write_text_atomically(csv_path, "\n".join(lines) + "\n")
    write_text_atomically(tex_path, "\n".join(tables))
    modes = list(residuals)
    index = residuals[modes[0]][0]
    # barycentre residuals over every position, for the figure that shows why positions are selected
    all_index = datasets[modes[0]]["position"].values
    product = xr.Dataset(
        {"residual": (("mode", "position", "star", "axis"), np.stack([residuals[m][1] for m in modes]),
                      {"units": "pixel", "long_name": "Procrustes residual of each star"}),
         "accuracy": (("mode",), [next(r["accuracy"] for r in rows if r["mode"] == m and r["grouping"] == "position")
                                  for m in modes], {"units": "pixel", "long_name": "corrected accuracy (p)"}),
         "barycentre_residual": (("mode", "all_position", "star", "axis"),
                                 np.stack([_barycentre(astrometry.select_positions(datasets[m])[0])
                                           for m in modes]),
                                 {"units": "pixel", "long_name": "star minus the barycentre of the others, minus "
                                                                 "its mean over positions"})},
        coords={"mode": modes, "position": index, "all_position": all_index, "axis": ["x", "y"]})
    io.write_product(product, residuals_path, title="Procrustes residuals per calibration mode", config=config,
                     inputs=list(centroid_paths))


dice_core.run_logged(snakemake.log[0], accuracy_table, list(snakemake.input.centroids), snakemake.output.csv,
                     snakemake.output.tex, snakemake.output.residuals, snakemake.config)
