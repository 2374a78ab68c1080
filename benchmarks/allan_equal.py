"""Is the Allan product the same whatever the memory scheme? Another tree's against this one's, per baseline.

For each ``allan/<baseline>.nc`` a workflow run made under ``--results`` (e.g. of the ``ci`` or ``default``
preset), the Allan step is run again in fresh processes (benchmarks/allan_memory.py's job: the workflow
script's calls) from the same manifest, metrology product and dark: by the other tree (``--old-code``, e.g.
the base commit's ``git archive``) as it runs by default, and by this tree with ``--workers`` processes and
bands of ``--pixels-per-block`` pixels (several bands even on a small detector). Printed per baseline:
whether dims, coordinates and attributes agree, and the largest absolute difference of every variable that
differs (pixel for offsets and deviations).

    git archive <base> dice_core | tar -x -C /tmp/dice-base
    python -m snakemake --cores 2 --config dataset=ci results=/tmp/wf --until allan_deviation
    python benchmarks/allan_equal.py --results /tmp/wf/sim-ci --old-code /tmp/dice-base --pixels-per-block 100
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def main(argv=None):
    from allan_memory import differences, run_job

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--results", type=Path, required=True, help="a dataset's results folder")
    parser.add_argument("--old-code", type=Path, required=True, help="folder holding the other dice_core/")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--pixels-per-block", default="100")
    args = parser.parse_args(argv)
    manifest = args.results / "raw" / "dataset.yaml"
    dark = args.results / "calibration" / "dark.nc"
    out = {}
    with tempfile.TemporaryDirectory() as folder:
        for product in sorted((args.results / "allan").glob("*.nc")):
            baseline = product.stem
            runs = {}
            for name, tree, options in (("old", args.old_code, {}),
                                        ("new", REPO, {"workers": args.workers,
                                                       "pixels_per_block": args.pixels_per_block})):
                runs[name] = Path(folder) / f"{baseline}-{name}.nc"
                run_job(tree, manifest, args.results / "metrology" / f"{baseline}.nc", dark, baseline, runs[name],
                        **options)
            found = differences(runs["old"], runs["new"])
            found["max_difference"] = {k: v for k, v in found["max_difference"].items() if v != 0.0}
            out[baseline] = found
            print(baseline, json.dumps(found))
    return out


if __name__ == "__main__":
    sys.path[:0] = [str(REPO), str(REPO / "benchmarks")]
    main()
