"""Several wavelengths through the workflow: time and memory against the number of laser wavelengths (issue 26).

For each number of wavelengths N given (1, 2, 3, 5: the chromatic study's calibration sets,
``dice_core.studies.CALIBRATION_WAVELENGTHS``, 633 nm first), one run of the README's command,

    python -m snakemake --cores 2 --configfile <workdir>/<N>.yaml

on the ``chromatic`` preset (config ``dataset: chromatic``) with ``simulation:`` overrides: the lasers and the
laser flats at those N wavelengths, and a larger detector (``--shape``, 512x512 by default) so that the per-pixel
memory shows beside the interpreter's. Each run simulates and reduces its own dataset (the whole default
target: every wavelength's fits, offsets, Allan deviations, calibration/chromatic.nc where N >= 2, every
centroid mode). Snakemake's ``benchmark:`` files give each job's wall time and peak memory (the whole job: start,
imports, inputs, the step, the product); the command's wall time is measured around it. Printed: per N, the
run's wall time, the summed job time of each kind of job, and the peak memory of the steps whose inputs grow
with N (``chromatic_calibration``, the chromatic mode's ``measure_centroids``); then, for BENCHMARKS.md, each
quantity per wavelength against N. Every run's numbers go to ``<workdir>/<N>.json``.

    python benchmarks/chromatic.py --workdir /tmp/dice-chromatic 1 2 3 5
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

import yaml
from user_path import benchmark_record, snakemake


def overrides(n: int, rows: int, cols: int) -> dict:
    """The chromatic preset's ``simulation:`` overrides for N wavelengths on a rows x cols detector."""
    from dice_core.studies import CALIBRATION_WAVELENGTHS

    wavelengths = sorted(CALIBRATION_WAVELENGTHS[n], key=lambda w: abs(w - 633e-9) > 1e-12)  # 633 nm first
    return {"metrology.wavelengths": [float(w) for w in wavelengths],
            "flats.wavelengths": [float(w) for w in wavelengths],
            "detector.shape": [rows, cols], "detector.science_rows": [2, rows - 2],
            "detector.science_cols": [4, cols - 2]}


def run(workdir: Path, n: int, rows: int, cols: int) -> dict:
    config = workdir / f"{n}.yaml"
    config.write_text(yaml.safe_dump({"dataset": "chromatic", "results": str(workdir / f"results-{n}"),
                                      "simulation": overrides(n, rows, cols)}))
    wall = snakemake("--configfile", str(config), echo=True).wall_s
    jobs = defaultdict(list)
    for tsv in (workdir / f"results-{n}").glob("*/benchmarks/*.tsv"):
        record = benchmark_record(tsv)
        step = tsv.stem
        for prefix in ("measure_centroids_flat+metrology+chromatic", "chromatic_calibration", "measure_centroids",
                       "fit_fringes", "allan_deviation", "measure_prnu", "simulate_file", "stack_position"):
            if step.startswith(prefix):
                step = prefix
                break
        jobs[step].append((record["s"], record["max_rss"]))
    summary = {step: {"jobs": len(v), "seconds": sum(s for s, _ in v), "peak_mb": max(m for _, m in v)}
               for step, v in sorted(jobs.items())}
    result = {"wavelengths": n, "shape": [rows, cols], "wall_s": wall, "steps": summary}
    (workdir / f"{n}.json").write_text(json.dumps(result, indent=1))
    return result


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("counts", nargs="+", type=int, help="numbers of wavelengths (1, 2, 3, 5)")
    parser.add_argument("--workdir", type=Path, required=True)
    parser.add_argument("--shape", default="512x512", help="rows x cols of the detector")
    args = parser.parse_args(argv)
    rows, cols = (int(v) for v in args.shape.split("x"))
    args.workdir.mkdir(parents=True, exist_ok=True)
    results = [run(args.workdir, n, rows, cols) for n in args.counts]
    print("\n| wavelengths | wall (s) | job time (s) | fit_fringes jobs, s | chromatic_calibration (s, MB) | "
          "chromatic mode's centroids (s, MB) |\n|---:|---:|---:|---|---|---|")
    for r in results:
        steps = r["steps"]
        total = sum(s["seconds"] for s in steps.values())

        def cell(name):
            s = steps.get(name)
            return "-" if s is None else f"{s['seconds']:.1f}, {s['peak_mb']:.0f}"

        fits = steps.get("fit_fringes", {"jobs": 0, "seconds": 0.0})
        print(f"| {r['wavelengths']} | {r['wall_s']:.0f} | {total:.0f} | {fits['jobs']}, {fits['seconds']:.0f} | "
              f"{cell('chromatic_calibration')} | {cell('measure_centroids_flat+metrology+chromatic')} |")


if __name__ == "__main__":
    main()
