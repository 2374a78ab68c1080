"""Snakemake step: one row per point of a sweep, its parameters and every scalar (or per-mode) result (CSV)."""

import csv
import io as text_io
import json

import dice_core
from dice_core import io


def sweep_summary(points, output):
    rows, columns = [], []
    for path in points:
        ds = io.read_product(path)
        point = json.loads(ds.attrs["configuration"])["point"]
        row = dict(point)
        for name, var in ds.data_vars.items():
            if var.ndim == 0:
                row[f"{name} [{var.attrs['units']}]"] = float(var.values)
            elif var.dims == ("mode",):  # a study's per-mode results (star_accuracy)
                row.update({f"{name}[{mode}] [{var.attrs['units']}]": float(value)
                            for mode, value in zip(ds["mode"].values, var.values)})
        rows.append(row)
        columns += [c for c in row if c not in columns]
    buffer = text_io.StringIO()
    writer = csv.DictWriter(buffer, columns, lineterminator="\n")
    writer.writeheader()
    writer.writerows({k: (f"{v:.6e}" if isinstance(v, float) else v) for k, v in row.items()} for row in rows)
    io.write_text(output, buffer.getvalue())


dice_core.run_logged(snakemake.log[0], sweep_summary, list(snakemake.input.points), snakemake.output.csv)
