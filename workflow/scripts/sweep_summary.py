"""Snakemake step: one row per point of a sweep, its parameters and every scalar (or per-mode, per-model) result (CSV)."""

import csv
import io as text_io
import json

import dice_core
from dice_core import io


def sweep_summary(points, output):
    rows, columns = [], []
    for path in points:
        ds = io.read_product(path)
        point = json.loads(ds.attrs["point"])
        row = dict(point)
        for name, var in ds.data_vars.items():
            if var.ndim == 0:
                row[f"{name} [{var.attrs['units']}]"] = float(var.values)
            elif var.ndim == 1 and var.dims[0] in ds.coords:  # per-mode (star_accuracy), per-model (tip_tilt)
                row.update({f"{name}[{key}] [{var.attrs['units']}]": float(value)
                            for key, value in zip(ds[var.dims[0]].values, var.values)})
        rows.append(row)
        columns += [c for c in row if c not in columns]
    buffer = text_io.StringIO()
    writer = csv.DictWriter(buffer, columns, lineterminator="\n")
    writer.writeheader()
    writer.writerows({k: (f"{v:.6e}" if isinstance(v, float) else v) for k, v in row.items()} for row in rows)
    io.write_text(output, buffer.getvalue())


dice_core.run_logged(snakemake.log[0], sweep_summary, list(snakemake.input.points), snakemake.output.csv)
