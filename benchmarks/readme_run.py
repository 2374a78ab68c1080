"""A preset on the path users take: the README's main command timed, beside a plain read of all its raw files.

In one run, with the repository's code and the README's command (``python -m snakemake --cores 2`` with
``--config dataset=<preset>``), into a results folder of its own:

1. the simulation alone: Snakemake with the dataset's manifest as its target, from nothing;
2. one plain read of every raw file the manifest names, in a fresh single process: each acquisition
   streamed in the reductions' chunks, converted to float32 as they read it and summed over frames (the
   pass alone, imports excluded);
3. the reduction: the same command with no target, everything after the simulation;
4. the plain read again, to bracket the machine's noise.

With ``--whole``, 1 and 3 are one command, the README's main command as a user types it (simulation and
reduction together, no target), and the plain read follows it.

The ratio of the reduction's wall time to the plain read (the mean of the two) is the one issue 28
asks of the paper preset on shared cores: at most 6; its targets on idle cores are a simulation under 90 s
and a reduction under 60 s, and the default preset's whole command under 60 s. The load average is
printed before and after each phase, each command's job seconds summed by rule, and each step's peak
RSS from the jobs' benchmark files.

Usage::

    python benchmarks/readme_run.py --workdir /tmp/dice-paper-run                    # the paper preset
    python benchmarks/readme_run.py --workdir /tmp/dice-default-run --dataset default --whole

Prints a Markdown table for BENCHMARKS.md. ``--workdir`` is emptied first (its ``results/`` would
otherwise make Snakemake skip work). Called ``paper_run.py`` before it took ``--dataset`` and ``--whole``.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import time
from pathlib import Path

import job_resources  # a benchmark script beside this one (its folder is first on sys.path)
from user_path import job_seconds, machine, plain_read, snakemake


def load():
    """The 1-minute load average, as ``uptime`` says it."""
    return os.getloadavg()[0]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/dice-readme-run"))
    parser.add_argument("--dataset", default="paper", help="a preset's name (config/presets/<name>.yaml)")
    parser.add_argument("--whole", action="store_true",
                        help="simulation and reduction in one command, the README's main command as typed")
    args = parser.parse_args(argv)
    shutil.rmtree(args.workdir, ignore_errors=True)
    args.workdir.mkdir(parents=True)
    results = args.workdir / "results"
    manifest = results / f"sim-{args.dataset}" / "raw" / "dataset.yaml"
    print(f"machine: {machine()}; started {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}",
          file=sys.stderr)
    rows, reads, by_rule = [], [], {}

    def workflow(name, *targets):
        before = load()
        run = snakemake("--config", f"dataset={args.dataset}", f"results={results}", "--", *targets)
        rows.append((name, f"{run.wall_s:.1f} s, {run.jobs} jobs", before, load()))
        by_rule[name] = job_seconds(run.log)
        return run.wall_s

    def read(when):
        before = load()
        done = plain_read(manifest)
        reads.append(done["seconds"])
        rows.append((f"plain read of the {done['files']} raw files ({done['frames']} frames, "
                     f"{done['samples'] * 2 / 1e9:.3g} GB of uint16), {when}", f"{done['seconds']:.1f} s",
                     before, load()))

    if args.whole:
        reduction = workflow("the whole command (simulation and reduction, no target)")
        read("after the command")
    else:
        workflow("simulation (the manifest as target)", str(manifest))
        read("before the reduction")
        reduction = workflow("reduction (no target)")
        read("after the reduction")
    print(f"{args.dataset} preset\n\n| phase | wall | load before | load after |\n|---|---:|---:|---:|")
    for name, value, start, end in rows:
        print(f"| {name} | {value} | {start:.1f} | {end:.1f} |")
    print(f"\n{'command' if args.whole else 'reduction'} / plain read: {reduction / (sum(reads) / len(reads)):.2f} "
          f"(the reads {', '.join(f'{r:.1f}' for r in reads)} s)")
    for name, seconds in by_rule.items():
        print(f"\n{name}, job seconds by rule (Snakemake's log, whole seconds, {sum(seconds.values()):.0f} in all): "
              + ", ".join(f"{rule} {value:.0f}" for rule, value in seconds.items()))
    peaks = {}
    for step, *_, rss, _, _ in job_resources.jobs(results / f"sim-{args.dataset}"):
        peaks[step] = max(peaks.get(step, 0.0), rss)
    print("\npeak RSS by step (MB, the benchmark files of the jobs that have one: a job's processes summed): "
          + ", ".join(f"{step} {mb:.0f}" for step, mb in sorted(peaks.items(), key=lambda item: -item[1])))


if __name__ == "__main__":
    main()
