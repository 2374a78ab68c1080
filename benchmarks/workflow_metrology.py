"""The metrology stage on the path users take: ``snakemake --cores 2`` on one 200,000-frame baseline.

Simulates (once, cached in --workdir) a dataset with a dark, two flats and one
80x84 metrology baseline of N frames (default 200,000: 2.7 GB of uint16 in
files of 20,000 frames; the paper preset's noise), then, in one run:

1. one plain read pass of the baseline's files in a fresh single process: the
   same chunks, converted to float32 as the reductions read them and summed
   over frames (the time of the pass alone, imports excluded); and the same
   pass in float64, FrameStream's default type;
2. the workflow's own command, ``python -m snakemake --cores 2`` with
   ``--config dataset=<manifest>``, for the baseline's ``metrology/`` and
   ``allan/`` products (``--forcerun`` makes the fit and the Allan step run
   again each repeat): each job's time and peak memory come from the rule's
   ``benchmark:`` file, which Snakemake writes around the whole job (process
   start, imports, reading the inputs, the reduction, writing the product);
3. the plain pass again, after the workflow, to bracket the machine's noise.

Usage::

    python benchmarks/workflow_metrology.py --frames 200000 --workdir /tmp/dice-workflow-bench

Prints a Markdown table for BENCHMARKS.md; ratios are taken within the run.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import sys
import time
from pathlib import Path

from user_path import REPO, benchmark_record, machine, plain_read, snakemake

BASELINE = "H1H4"


def config(frames, frames_per_file=20000):
    from dice_core import simulation

    return simulation.SimulationConfig.from_dict({
        "name": "workflow-bench", "seed": 20150926, "frames_per_file": frames_per_file,
        "detector": {"shape": [80, 84], "science_rows": [2, 79], "science_cols": [10, 83],
                     "gain": 10.0, "read_noise": 4.0},
        "dark": {"frames": 400}, "flats": {"frames": 400, "level": 20000.0},
        "stars": {"positions": 1, "frames": 1},
        "metrology": {"frames": frames, "sweep_frames": 1000, "mean_level": 10000.0, "amplitude": 6000.0,
                      "baselines": {BASELINE: {"period": 2.4, "angle_deg": 2.0}}, "pairs": {}},
    })


def _write(frames, frames_per_file, relpath, outdir):
    from dice_core import simulation
    from dice_core.io import read_product

    cfg = config(frames, frames_per_file)
    simulation.write_file(cfg, read_product(Path(outdir) / "truth.nc"), relpath=relpath, outdir=outdir)


def prepare(frames, data, frames_per_file=20000):
    """Simulate the dataset into ``data`` (two processes, one file each at a time), unless already there."""
    from dice_core import simulation
    from dice_core.io import write_product

    manifest = data / "dataset.yaml"
    if manifest.exists():
        return manifest
    cfg = config(frames, frames_per_file)
    write_product(simulation.make_truth(cfg), data / "truth.nc", title="benchmark truth")
    start = time.perf_counter()
    with concurrent.futures.ProcessPoolExecutor(2) as pool:
        list(pool.map(_write, *zip(*[(frames, frames_per_file, relpath, data)
                                     for relpath in simulation.file_jobs(cfg)])))
    simulation.write_manifest(cfg, data)
    print(f"simulated {frames} frames in {time.perf_counter() - start:.0f} s", file=sys.stderr)
    return manifest


def plain_pass(manifest, dtype="float32"):
    """Seconds of one plain read pass of the baseline in a fresh process (pass alone, imports excluded)."""
    return plain_read(manifest, BASELINE, dtype=dtype)["seconds"]


def run_workflow(manifest, results, name):
    """The README's command for the baseline's two products, the fit and Allan jobs forced to run: the
    command's wall time (s) and each job's (s, peak RSS MB) from its ``benchmark:`` file."""
    targets = [f"{results}/{name}/metrology/{BASELINE}.nc", f"{results}/{name}/allan/{BASELINE}.nc"]
    run = snakemake("--config", f"dataset={manifest}", f"results={results}",
                    "--forcerun", "fit_fringes", "allan_deviation", "--", *targets)
    bench = Path(results) / name / "benchmarks"
    fit, allan = (benchmark_record(bench / f"{job}_{BASELINE}.tsv") for job in ("fit_fringes", "allan_deviation"))
    return run.wall_s, (fit["s"], fit["max_rss"]), (allan["s"], allan["max_rss"])


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=200000)
    parser.add_argument("--workdir", type=Path, default=REPO / "benchmarks" / "out" / "workflow")
    parser.add_argument("--repeat", type=int, default=2, help="workflow runs (each after a plain pass)")
    args = parser.parse_args()
    data = (args.workdir / f"n{args.frames}").resolve()
    manifest = prepare(args.frames, data)
    results = data / "results"
    print(f"machine: {machine()}")
    print(f"{args.frames} frames of 80x84 in {len(list((data / 'metrology').glob('**/*.fits')))} files\n")
    plain_pass(manifest)  # warm the page cache: every timing reads from memory
    print("| run | plain pass float32 (s) | plain pass float64 (s) | fit_fringes job (s) | / float32 pass "
          "| / float64 pass | allan_deviation job (s) | / float32 pass | / float64 pass | fit peak RSS (MiB) "
          "| Allan peak RSS (MiB) | snakemake command (s) |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for run in range(1, args.repeat + 1):
        before = plain_pass(manifest), plain_pass(manifest, "float64")
        wall, (fit_s, fit_rss), (allan_s, allan_rss) = run_workflow(manifest, results, "workflow-bench")
        after = plain_pass(manifest), plain_pass(manifest, "float64")
        p32, p64 = min(before[0], after[0]), min(before[1], after[1])
        print(f"| {run} | {p32:.2f} | {p64:.2f} | {fit_s:.2f} | {fit_s / p32:.2f} | {fit_s / p64:.2f} | {allan_s:.2f} "
              f"| {allan_s / p32:.2f} | {allan_s / p64:.2f} | {fit_rss:.0f} | {allan_rss:.0f} | {wall:.1f} |",
              flush=True)
    print("\nEach plain pass is the faster of the two run just before and just after the workflow.")


if __name__ == "__main__":
    main()
