"""What the workflow benchmarks share: the README's command run as a user runs it, its jobs' records, and the
plain read that their times are quoted against.

Not a benchmark itself: the scripts beside it import it (``sys.path`` holds their folder when run as
``python benchmarks/<script>.py``).
"""

from __future__ import annotations

import csv
import json
import os
import platform
import re
import subprocess
import sys
import time
from collections import defaultdict
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def machine() -> str:
    """Cores, CPU model, Python and numpy versions of this machine, for a benchmark's header."""
    cpu = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                if line.startswith("model name")), platform.processor())
    import numpy

    return f"{os.cpu_count()} cores ({cpu}), Python {platform.python_version()}, numpy {numpy.__version__}"


@dataclass(frozen=True)
class Run:
    """One finished Snakemake command: its wall time (s) and its log (Snakemake's stderr)."""

    wall_s: float
    log: str

    @property
    def jobs(self) -> int:
        """Jobs the command ran."""
        return self.log.count("Finished jobid")


def snakemake(*arguments: str, cores: int = 2, tree: Path = REPO, env: dict | None = None, echo: bool = False) -> Run:
    """The README's command, ``python -m snakemake --cores 2`` followed by ``arguments``, run from ``tree`` (a
    checkout of the repository: its Snakefile and, through the working directory, its ``dice_core``).

    Exits with the command and the end of Snakemake's log when it fails: a benchmark's numbers mean nothing
    once a job has failed.
    """
    cmd = [sys.executable, "-m", "snakemake", "--cores", str(cores), *arguments]
    if echo:
        print(f"$ {' '.join(cmd)}", flush=True)
    start = time.perf_counter()
    done = subprocess.run(cmd, cwd=tree, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - start
    if done.returncode:
        sys.exit(f"{' '.join(cmd)} failed after {wall:.0f} s:\n{done.stderr[-5000:]}")
    return Run(wall, done.stderr)


def benchmark_record(path: Path) -> dict[str, float]:
    """A job's ``benchmark:`` file (Snakemake's, around the whole job): ``s`` (wall), ``max_rss`` (MB),
    ``cpu_time`` (s; sampled, an undercount for jobs of a few seconds), as numbers."""
    with open(path, newline="") as handle:
        row = next(csv.DictReader(handle, delimiter="\t"))
    return {key: float(row[key]) for key in ("s", "max_rss", "cpu_time")}


def job_seconds(log: str) -> dict[str, float]:
    """Wall seconds of each job summed by rule (a group's rules as one: ``simulate_file``, ``stack_position``),
    from the start and end stamps of Snakemake's log (whole seconds, every job, figures included), largest
    first."""
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


#: The plain read (argv: manifest, dtype, then a baseline's name or none for every acquisition): each file
#: streamed in the reductions' chunks, converted to ``dtype`` and summed over frames, in one process. The
#: time is the reading alone, imports excluded.
PLAIN_READ = """
import json, sys, time
from dice_core.io import FrameStream
from dice_core.manifest import load_manifest
manifest = load_manifest(sys.argv[1])
dtype, baseline = sys.argv[2], sys.argv[3:]
acquisitions = [manifest.baselines[b] for b in baseline] or manifest.acquisitions()
start = time.perf_counter()
frames = samples = 0
for acquisition in acquisitions:
    stream = FrameStream(acquisition, manifest.detector, dtype=dtype)
    total = 0.0
    for chunk in stream:
        total = total + chunk.frames.sum(axis=0)
    frames += stream.n_frames
    samples += stream.n_frames * manifest.detector.shape[0] * manifest.detector.shape[1]
print(json.dumps({"seconds": time.perf_counter() - start, "frames": frames, "samples": samples,
                  "files": sum(len(a.files) for a in acquisitions)}))
"""


def plain_read(manifest: Path, baseline: str | None = None, *, dtype: str = "float32", tree: Path = REPO) -> dict:
    """:data:`PLAIN_READ` of a ``baseline`` (None: every acquisition of the manifest) in a fresh process with
    ``tree``'s ``dice_core``: ``seconds``, ``frames``, ``samples``, ``files``."""
    out = subprocess.run([sys.executable, "-c", PLAIN_READ, str(manifest), dtype, *([baseline] if baseline else [])],
                         check=True, capture_output=True, text=True, cwd=tree,
                         env={**os.environ, "PYTHONPATH": str(Path(tree).resolve())}).stdout
    return json.loads(out)


#: Defines ``status(key)`` in a benchmark's child process (the scripts add it to the code they run with
#: ``python -c``): a field of /proc/self/status in MiB (``VmRSS``, ``VmHWM``).
PROC_STATUS = '''
def status(key):
    for line in open("/proc/self/status"):
        if line.startswith(key):
            return int(line.split()[1]) / 1024
'''
