"""Snakemake step: the reproduction report as one PDF, the figures with their captions after the comparison table."""

import csv
import textwrap
from pathlib import Path

import dice_core
from dice_core import plotting


def paper_pdf(figures, captions, comparison, output, dataset):
    with open(comparison, newline="") as handle:
        rows = list(csv.DictReader(handle))
    lines = [f"dataset {dataset}; dice_core {dice_core.__version__}; Crouzier et al. (A&A), the DICE paper", "",
             f"{'quantity':<74} {'paper':>9} {'ours':>10} {'error':>9}  unit   source"]
    for row in rows:
        lines.append(f"{row['quantity'][:74]:<74} {row['paper']:>9} {row['ours']:>10} {row['error']:>9}  "
                     f"{row['unit']:<6} {row['dataset']}")
        lines += [f"    {part}" for part in textwrap.wrap(row["note"], 150)]
    pages = [(png, Path(caption).read_text().strip()) for png, caption in zip(figures, captions)]
    plotting.reproduction_pdf(output, pages, title="DICE reduction: the paper regenerated", summary_lines=lines)


dice_core.run_logged(snakemake.log[0], paper_pdf, list(snakemake.input.figures), list(snakemake.input.captions),
                     snakemake.input.comparison, snakemake.output.pdf, snakemake.params.dataset)
