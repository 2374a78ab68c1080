"""Snakemake step: every regenerated number of the paper beside the paper's, tables/paper_comparison.csv."""

import csv
import logging

import dice_core
from dice_core import io, plotting, reproduction


def read_csv(path):
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def paper_comparison(inputs, csv_path, png, pdf, dataset, positions, method, stray_light):
    log = logging.getLogger("dice")
    points = {}
    for path in inputs["offset_bias"]:
        ds = io.read_product(path)
        prnu = float(ds.attrs["prnu_rms"])
        if prnu in points:
            raise ValueError(f"{path}: a second point at PRNU RSD {prnu:g}: the paper's offset-bias sweep (config "
                             "paper.offset_bias) must vary the PRNU alone")
        points[prnu] = ds
    rows = reproduction.offset_bias_rows(points)
    rows += reproduction.error_propagation_rows(read_csv(inputs["error_propagation"]))
    rows += reproduction.chromatic_rows([io.read_product(path) for path in inputs["chromatic"]])
    (deflation,) = read_csv(inputs["deflation"])
    rows.append(reproduction.Row("deflation", float(deflation["factor"]), float(deflation["error"]), "nominal geometry",
                                 f"{deflation['trials']} Monte Carlo trials of white jitter"))
    strays = {ds.attrs["baseline"]: ds for ds in map(io.read_product, inputs.get("stray_light", []))}
    for path in inputs.get("allan", []):
        allan = io.read_product(path)
        found = reproduction.stray_light_note(strays[allan.attrs["baseline"]]) if allan.attrs.get(
            "baseline") in strays else ""
        for row in reproduction.allan_rows(allan, dataset=dataset):
            row.note += f"; {found}" if found else ""
            rows.append(row)
    rows += reproduction.stray_light_study_rows([io.read_product(p) for p in inputs["stray_light_study"]])
    for stray in strays.values():
        rows += reproduction.stray_light_rows(stray, dataset=dataset, removed=stray_light == "remove")
    if "accuracy" in inputs:
        used = "all positions" if positions is None else f"positions {positions[0]}-{positions[1]}"
        records = [r for r in read_csv(inputs["accuracy"]) if r["method"] == method]
        rows += reproduction.accuracy_rows(records, dataset=dataset, note=f"simulated bench, {used}, method {method}")
    for row in rows:
        values = row.as_dict()
        log.info("%-90s paper %-9.3g ours %.3g +- %.2g %s", values["quantity"], values["paper"], values["ours"],
                 values["error"], values["unit"])
    io.write_text(csv_path, reproduction.comparison_csv(rows))
    # the figure sets ours over the paper's: the rows of ours alone (each offset-bias map's rms) are in the table
    plotting.save(plotting.paper_comparison_figure([r for r in rows if r.key is not None]), png, pdf=pdf)


inputs = {key: (list(value) if not isinstance(value, str) else value) for key, value in snakemake.input.items()}
dice_core.run_logged(snakemake.log[0], paper_comparison, inputs, snakemake.output.csv, snakemake.output.png,
                     snakemake.output.pdf, snakemake.params.dataset,
                     snakemake.params.settings["astrometry"]["positions"],
                     snakemake.params.settings["centroids"]["method"],
                     snakemake.params.settings["metrology"]["stray_light"])
