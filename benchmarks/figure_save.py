"""A figure's two saves: the PNG, then the PDF laid out again (as before) or with the PNG's layout kept.

Builds the default preset's metrology figure (``plotting.metrology_figure``) from a ``metrology/<baseline>.nc``
product of a finished run, and times its PNG save and its PDF save both ways, alternating over ``--repeats``
rounds in one process (imports and reading excluded); prints the medians and the largest move of an axes
between the two PDFs' layouts, in figure fractions.

    python benchmarks/figure_save.py results/sim-default [--repeats 5]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from dice_core import io, plotting
from dice_core.manifest import load_manifest


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", type=Path, help="a finished run's results/<name>/ folder")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)
    detector = load_manifest(args.results / "raw" / "dataset.yaml", check_files=False).detector
    product = io.read_product(sorted((args.results / "metrology").glob("*.nc"))[0])
    times = {"png": [], "pdf laid out again": [], "pdf, the png's layout kept": []}
    moved = 0.0
    with tempfile.TemporaryDirectory() as out:
        for _ in range(args.repeats):
            positions = []
            for keep in (False, True):
                fig = plotting.metrology_figure(product, detector, title="Metrology")
                start = time.perf_counter()
                fig.savefig(f"{out}/f.png", dpi=150)
                times["png"].append(time.perf_counter() - start)
                if keep:
                    fig.set_layout_engine("none")
                start = time.perf_counter()
                fig.savefig(f"{out}/f.pdf", dpi=150)
                times["pdf, the png's layout kept" if keep else "pdf laid out again"].append(
                    time.perf_counter() - start)
                positions.append(np.array([ax.get_position().bounds for ax in fig.axes]))
                plotting.plt.close(fig)
            moved = max(moved, float(np.abs(positions[0] - positions[1]).max()))
    for name, values in times.items():
        print(f"{name}: median {statistics.median(values):.2f} s over {len(values)}")
    print(f"largest move of an axes between the two PDFs' layouts: {moved:.1e} of the figure")


if __name__ == "__main__":
    main()
