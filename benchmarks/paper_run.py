"""The paper preset on the path users take, its reduction timed beside a plain read of all its raw files.

In one run, with the repository's code and the README's command (``python -m snakemake --cores 2`` with
``--config dataset=paper``), into a results folder of its own:

1. the simulation alone: Snakemake with the dataset's manifest as its target, from nothing;
2. one plain read of every raw file the manifest names, in a fresh single process: each acquisition
   streamed in the reductions' chunks, converted to float32 as they read it and summed over frames (the
   pass alone, imports excluded);
3. the reduction: the same command with no target, everything after the simulation;
4. the plain read again, to bracket the machine's noise.

The ratio of the reduction's wall time to the plain read (the mean of the two) is the one issue 28
asks of a run on shared cores: at most 6. The load average is printed before and after each phase.

Usage::

    python benchmarks/paper_run.py --workdir /tmp/dice-paper-run

Prints a Markdown table for BENCHMARKS.md. ``--workdir`` is emptied first (its ``results/`` would
otherwise make Snakemake skip work).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import time
from collections import defaultdict
from datetime import datetime
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from workflow_metrology import machine  # noqa: E402  (a benchmark script beside this one, not a package)

PLAIN_READ = """
import json, sys, time
from dice_core.io import FrameStream
from dice_core.manifest import load_manifest
manifest = load_manifest(sys.argv[1])
start = time.perf_counter()
frames = samples = 0
for acquisition in manifest.acquisitions():
    stream = FrameStream(acquisition, manifest.detector, dtype="float32")
    total = 0.0
    for chunk in stream:
        total = total + chunk.frames.sum(axis=0)
    frames += stream.n_frames
    samples += stream.n_frames * manifest.detector.shape[0] * manifest.detector.shape[1]
print(json.dumps({"seconds": time.perf_counter() - start, "frames": frames, "samples": samples,
                  "files": len(manifest.all_files())}))
"""


def load():
    """The 1-minute load average, as ``uptime`` says it."""
    return os.getloadavg()[0]


def job_seconds(log: str) -> dict:
    """Wall seconds of each job summed by rule (a group's rules as one: ``simulate_file``, ``stack_position``),
    from the start and end stamps of Snakemake's log (whole seconds, every job, figures included)."""
    stamp, started, rule_of, totals = None, {}, {}, defaultdict(float)
    rule = None
    for line in log.splitlines():
        if found := re.match(r"\[(\w{3} \w{3} +\d+ [\d:]{8} \d{4})\]", line):
            stamp = datetime.strptime(" ".join(found.group(1).split()), "%a %b %d %H:%M:%S %Y")
        elif found := re.match(r"(?:local)?rule (\S+):", line):
            rule = re.sub(r"_\d+(_to_\d+)?$", "", found.group(1))
        elif (found := re.match(r"\s+jobid: (\d+)", line)) and rule:
            started[found.group(1)], rule_of[found.group(1)], rule = stamp, rule, None
        elif found := re.match(r"Finished jobid: (\d+)", line):
            totals[rule_of[found.group(1)]] += (stamp - started[found.group(1)]).total_seconds()
    return dict(sorted(totals.items(), key=lambda item: -item[1]))


def snakemake(workdir, *targets):
    """Wall seconds, jobs done and job seconds by rule (:func:`job_seconds`) of the README's command on the
    paper preset, results in ``workdir``."""
    cmd = [sys.executable, "-m", "snakemake", "--cores", "2", "--config", "dataset=paper",
           f"results={workdir}/results", "--", *targets]
    start = time.perf_counter()
    done = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    wall = time.perf_counter() - start
    if done.returncode:
        sys.exit(f"{' '.join(cmd)} failed:\n{done.stderr[-3000:]}")
    return wall, done.stderr.count("Finished jobid"), job_seconds(done.stderr)


def plain_read(manifest):
    """The plain read of every raw file, in a fresh process: {seconds, frames, samples, files}."""
    out = subprocess.run([sys.executable, "-c", PLAIN_READ, str(manifest)], cwd=REPO, check=True,
                         capture_output=True, text=True).stdout
    return json.loads(out)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/dice-paper-run"))
    args = parser.parse_args(argv)
    shutil.rmtree(args.workdir, ignore_errors=True)
    args.workdir.mkdir(parents=True)
    manifest = args.workdir / "results" / "sim-paper" / "raw" / "dataset.yaml"
    print(f"machine: {machine()}; started {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}",
          file=sys.stderr)
    rows, reads = [], []

    by_rule = {}

    def workflow(name, *targets):
        before = load()
        wall, jobs, seconds = snakemake(args.workdir, *targets)
        rows.append((name, f"{wall:.0f} s, {jobs} jobs", before, load()))
        by_rule[name] = seconds
        return wall

    def read(when):
        before = load()
        done = plain_read(manifest)
        reads.append(done["seconds"])
        rows.append((f"plain read of the {done['files']} raw files ({done['frames']} frames, "
                     f"{done['samples'] * 2 / 1e9:.1f} GB of uint16), {when}", f"{done['seconds']:.1f} s",
                     before, load()))

    workflow("simulation (the manifest as target)", str(manifest))
    read("before the reduction")
    reduction = workflow("reduction (no target)")
    read("after the reduction")
    ratio = reduction / (sum(reads) / len(reads))
    print("| phase | wall | load before | load after |\n|---|---:|---:|---:|")
    for name, value, start, end in rows:
        print(f"| {name} | {value} | {start:.1f} | {end:.1f} |")
    print(f"\nreduction / plain read: {ratio:.2f} (the reads {reads[0]:.1f} and {reads[1]:.1f} s); "
          "issue 28's target on shared cores: at most 6 (a reduction on 2 cores against a read in 1 process, "
          "as the issue defines it)")
    for name, seconds in by_rule.items():
        print(f"\n{name}, job seconds by rule (Snakemake's log, whole seconds, {sum(seconds.values()):.0f} in all): "
              + ", ".join(f"{rule} {value:.0f}" for rule, value in seconds.items()))


if __name__ == "__main__":
    main()
