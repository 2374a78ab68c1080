"""Snakemake step: accuracies of every centroid mode and superimposition, as tables/accuracy.csv and LaTeX."""

import logging

import numpy as np

import dice_core
from dice_core import accuracies, io, superimposition


def accuracy_table(centroid_paths, csv_path, tex_path, residual_paths, config):
    log = logging.getLogger("dice")
    options = config["astrometry"]
    pose = options.get("pose", {})
    geometry = superimposition.PoseGeometry(pose.get("distance", 25000.0), np.radians(pose.get("off_axis_deg", 2.0)),
                                            pose.get("centre"))
    methods = list(dict.fromkeys([config["centroids"]["method"], *config["centroids"]["methods"]]))
    tables = accuracies.accuracy_tables(
        [io.read_product(path) for path in centroid_paths], methods,
        models=superimposition.configured_superimpositions(options.get("superimposition", "procrustes")),
        positions=options["positions"], groups=options["groups"], trials=options["trials"], geometry=geometry)
    for row in tables.rows:
        log.info("%-8s mode %-15s %-10s %-8s n=%-3d accuracy %.2e +- %.1e pixel (rms residual %.2e x factor %.3f)",
                 row["method"], row["mode"], row["superimposition"], row["grouping"], row["n"], row["accuracy"],
                 row["error"], row["rms_residual"], row["factor"])
    for name, report in tables.reports.items():
        log.info("%s: %s", name, report)
    io.write_text(csv_path, accuracies.accuracy_csv(tables.rows))
    io.write_text(tex_path, tables.latex)
    for model, path in residual_paths.items():
        io.write_product(tables.residuals[model], path, title=f"{model} residuals per calibration mode",
                         config=config, inputs=list(centroid_paths))


dice_core.run_logged(snakemake.log[0], accuracy_table, list(snakemake.input.centroids), snakemake.output.csv,
                     snakemake.output.tex,
                     {"procrustes": snakemake.output.residuals,
                      **{m: p for m, p in zip(snakemake.params.models, snakemake.output.model_residuals)}},
                     snakemake.params.settings,
                     provenance={"code_version": snakemake.params.code, **snakemake.params.roots})
