"""Time of the gauge (:func:`dice_core.fringes.fix_gauge`) and the tips' refinement
(:func:`dice_core.geometry.fit_two_source`) in blocks of pixels against one block of every pixel.

On a noiseless rank-3 factorisation of fringes over ``--shape`` pixels (the tests' ``gauge_case``, a
spherical bench's pixel phases for the tips), alternating the block sizes over ``--repeats`` rounds in one
process (one BLAS thread), the median time of each. One block of every pixel costs what the whole-array
formulas cost (the same QR, one block); the default block is :data:`dice_core.pixel_blocks.PIXEL_BLOCK`.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=$PWD python benchmarks/gauge_blocks.py --shape 1024 1024 --repeats 3
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--shape", type=int, nargs=2, default=(1024, 1024))
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    from dice_core import fringes, geometry
    from dice_core.pixel_blocks import PIXEL_BLOCK
    from test_fringes import gauge_case
    from test_geometry import PITCH, WAVELENGTH, two_source_case

    rows, cols = args.shape
    rng = np.random.default_rng(1)
    F, G, x, y, flat, _ = gauge_case(rng, shape=(rows, cols), centre=(cols / 2, rows / 2), width=1.5 * max(rows, cols))
    theta, tx, ty, _, nominal, k_plane = two_source_case(rng, shape=(rows, cols), origin=(0, 0), dead=0.0)
    cases = {
        "fix_gauge, flat": lambda block: fringes.fix_gauge(F, G, flat=flat, x=x, y=y, block=block),
        "fix_gauge, PRNU-free": lambda block: fringes.fix_gauge(F, G, flat=None, x=x, y=y, block=block),
        "fit_two_source": lambda block: geometry.fit_two_source(theta, tx, ty, *nominal, wavelength=WAVELENGTH,
                                                                pixel_pitch=PITCH, k_plane=k_plane, block=block),
    }
    blocks = {f"blocks of {PIXEL_BLOCK}": PIXEL_BLOCK, "one block": x.size}
    times = {(case, name): [] for case in cases for name in blocks}
    for _ in range(args.repeats):
        for case, run in cases.items():
            for name, block in blocks.items():
                start = time.perf_counter()
                run(block)
                times[case, name].append(time.perf_counter() - start)
    print(f"{rows}x{cols} pixels, median of {args.repeats} (s):")
    for case in cases:
        row = {name: statistics.median(times[case, name]) for name in blocks}
        ratio = row[f"blocks of {PIXEL_BLOCK}"] / row["one block"]
        print(f"  {case:22s} " + "  ".join(f"{name}: {t:.2f}" for name, t in row.items()) + f"  ratio {ratio:.2f}")


if __name__ == "__main__":
    main()
