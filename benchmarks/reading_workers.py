"""One worker or two for a baseline's fit and Allan jobs, against the baseline's size, on the path users take.

The ``fit_fringes`` and ``allan_deviation`` jobs read a baseline in :data:`dice_core.parallel.LANES` parts,
in as many worker processes as the job has threads. A second worker halves the reading; it also costs a
fork, a pool and a core held from every other job for the job's whole life, most of which (process start,
imports, the solve, the product) is serial. This measures where the second worker starts to pay: for each
size given (frames of one 80x84 baseline in two files, the paper preset's noise), the README's command
runs the two jobs with ``--set-threads`` 1 and 2 in turn, ``--repeat`` times, and prints each job's wall
time and CPU time (Snakemake's ``benchmark:`` files: the whole job) and the ratio of the two walls.

    python benchmarks/reading_workers.py --workdir /tmp/dice-workers 5000 15000 50000 150000
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import workflow_metrology  # a benchmark script beside this one (its folder is first on sys.path)
from user_path import benchmark_record, machine, snakemake

BASELINE = workflow_metrology.BASELINE


def run(manifest, results, threads):
    """(fit, Allan) each as (wall s, CPU s) with ``threads`` for both jobs."""
    name = "workflow-bench"
    targets = [f"{results}/{name}/metrology/{BASELINE}.nc", f"{results}/{name}/allan/{BASELINE}.nc"]
    snakemake("--config", f"dataset={manifest}", f"results={results}",
              "--set-threads", f"fit_fringes={threads}", f"allan_deviation={threads}",
              "--forcerun", "fit_fringes", "allan_deviation", "--", *targets)
    records = (benchmark_record(Path(results) / name / "benchmarks" / f"{job}_{BASELINE}.tsv")
               for job in ("fit_fringes", "allan_deviation"))
    return [(record["s"], record["cpu_time"]) for record in records]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("frames", nargs="+", type=int)
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/dice-workers"))
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args(argv)
    print(f"machine: {machine()}; {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")
    print("| frames (samples) | job | 1 worker: wall, CPU (s) | 2 workers: wall, CPU (s) | 2 / 1 (median wall) |")
    print("|---|---|---|---|---:|")
    for frames in args.frames:
        data = (args.workdir / f"n{frames}").resolve()
        manifest = workflow_metrology.prepare(frames, data, frames_per_file=-(-frames // 2))  # two files
        times = {1: [], 2: []}
        for _ in range(args.repeat):
            for threads in (1, 2):
                times[threads].append(run(manifest, data / "results", threads))
        for j, job in enumerate(("fit_fringes", "allan_deviation")):
            cells = {t: "; ".join(f"{r[j][0]:.2f}, {r[j][1]:.2f}" for r in times[t]) for t in (1, 2)}
            ratio = statistics.median(r[j][0] for r in times[2]) / statistics.median(r[j][0] for r in times[1])
            print(f"| {frames} ({frames * 80 * 84:.1e}) | `{job}` | {cells[1]} | {cells[2]} | {ratio:.2f} |",
                  flush=True)


if __name__ == "__main__":
    main()
