"""Snakemake step: a reduction sweep's accuracy tables, one row per point, mode and grouping, and its figure."""

import csv
import io as text_io

import dice_core
from dice_core import io, plotting


def reduction_sweep_summary(tables, points, csv_path, png, pdf, sweep):
    rows = []
    for point, path in zip(points, tables):
        with open(path, newline="") as handle:
            records = list(csv.DictReader(handle))
        if not records:
            raise ValueError(f"{path}: an empty accuracy table")
        rows += [{**point, **record} for record in records]
    # the figure draws each superimposition in its own panel, Procrustes (the paper's) first
    figure = plotting.reduction_sweep_figure(rows, list(points[0]), title=f"sweep {sweep}")
    # the units in the column names, as every summary has them, from the accuracy tables' column unit
    rows = [{(f"{k} [{row.get('unit', 'pixel')}]" if k in ("accuracy", "error", "rms_residual") else k): v
             for k, v in row.items() if k != "unit"} for row in rows]
    columns = list(points[0]) + [c for c in rows[0] if c not in points[0]]
    buffer = text_io.StringIO()
    writer = csv.DictWriter(buffer, columns, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    io.write_text(csv_path, buffer.getvalue())
    plotting.save(figure, png, pdf=pdf)


dice_core.run_logged(snakemake.log[0], reduction_sweep_summary, list(snakemake.input.tables),
                     list(snakemake.params.points), snakemake.output.csv, snakemake.output.png, snakemake.output.pdf,
                     snakemake.wildcards.sweep)
