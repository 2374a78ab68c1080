"""A step's fixed cost: process start to its first log line, for a no-op step run the way the workflow runs one.

A throw-away workflow holds one Snakemake ``script:`` rule per import set; its script imports what a real
step's script imports (the stack step's ``dice_core`` modules, the centroid step's, a figure step's), then runs
a step that does nothing through :func:`dice_core.run_logged`, as every workflow step does. Snakemake runs each
job in a fresh Python process with its preamble (unpickling the job's ``snakemake`` object), as it runs the
workflow's. The fixed cost of a job is the time from its process's start (``/proc/<pid>/stat``) to the first
line of its log; its whole time is Snakemake's ``benchmark:`` file's. In the same run, for ratios:
``python3 -c pass`` (the interpreter alone) and the preamble's imports alone.

    python benchmarks/step_fixed_cost.py [--repeats 10] [--tree DIR]...

``--tree`` runs the jobs with the ``dice_core`` of another source tree (e.g. an older checkout extracted with
``git archive REV | tar -x -C DIR``) beside this one's, alternating, for a ratio in one run.
"""

from __future__ import annotations

import argparse
import csv
import datetime as dt
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

#: What a step's script imports, by the step it stands for.
IMPORTS = {
    "stack_position": "from dice_core import io, stacks\nfrom dice_core.manifest import load_manifest",
    "measure_centroids": "from dice_core import centroids, chromatic, io, stacks\n"
                         "from dice_core.manifest import load_manifest",
    "fit_fringes": "from dice_core import calibration, fringe_fit, io\nfrom dice_core.manifest import load_manifest",
    "plot (figures)": "from dice_core import io, plotting",
    # the libraries a stack job reaches once it reads its FITS files and writes its product: its floor
    "stack_position, and what its step uses": "from dice_core import io, stacks\n"
                                              "from dice_core.manifest import load_manifest\n"
                                              "import xarray, netCDF4\nfrom astropy.io import fits",
}

SCRIPT = '''import logging
import os
import time
import dice_core
{imports}


def started():
    """This process's start, seconds since the epoch (its /proc start time after boot)."""
    ticks = os.sysconf("SC_CLK_TCK")
    after_boot = int(open("/proc/self/stat").read().rsplit(")", 1)[1].split()[19]) / ticks
    # the boot's time from /proc/uptime (1/100 s), not /proc/stat's btime: whole seconds, which put up to a
    # second into every fixed cost, as it depended on the machine's boot
    boot = time.time() - float(open("/proc/uptime").read().split()[0])
    return boot + after_boot


def noop(path):
    with open(path, "w") as out:
        out.write(repr(started()))


dice_core.run_logged(snakemake.log[0], noop, snakemake.output[0])
'''
# (the last import set's libraries are imported before the first line: the job's time is then the floor of a
# stack job that reads and writes nothing, whatever the step's imports defer)

SNAKEFILE = '''
rule all:
    input: expand("out/{{name}}/{{i}}.txt", name={names}, i=range({repeats}))

{rules}
'''

RULE = '''
rule {name}:
    output: "out/{name}/{{i}}.txt"
    log: "logs/{name}/{{i}}.log"
    benchmark: "bench/{name}/{{i}}.tsv"
    script: "{name}.py"
'''


def first_line_time(log: Path) -> float:
    stamp = " ".join(log.read_text().splitlines()[0].split()[:2])
    return dt.datetime.strptime(stamp, "%Y-%m-%d %H:%M:%S,%f").timestamp()


def workflow(folder: Path, repeats: int):
    names = [f"step{i}" for i in range(len(IMPORTS))]
    for name, imports in zip(names, IMPORTS.values()):
        (folder / f"{name}.py").write_text(SCRIPT.format(imports=imports))
    (folder / "Snakefile").write_text(SNAKEFILE.format(names=names, repeats=repeats, rules="".join(
        RULE.format(name=name) for name in names)))
    return names


def run_tree(folder: Path, tree: Path, names, repeats: int):
    """Every no-op job once more with ``tree``'s dice_core: {step: ([fixed costs], [job times])}, seconds."""
    for sub in ("out", "logs", "bench"):
        subprocess.run(["rm", "-rf", str(folder / sub)], check=True)
    env = {**os.environ, "PYTHONPATH": str(tree)}
    # one core: the jobs one after the other, none waiting for a core another holds
    subprocess.run([sys.executable, "-m", "snakemake", "--cores", "1", "--quiet", "all", "-d", str(folder), "-s",
                    str(folder / "Snakefile")], check=True, env=env, capture_output=True)
    out = {}
    for step, name in zip(IMPORTS, names):
        fixed, job = [], []
        for i in range(repeats):
            start = float((folder / "out" / name / f"{i}.txt").read_text())
            fixed.append(first_line_time(folder / "logs" / name / f"{i}.log") - start)
            with open(folder / "bench" / name / f"{i}.tsv") as f:
                job.append(float(next(csv.DictReader(f, delimiter="\t"))["s"]))
        out[step] = (fixed, job)
    return out


def timed(command, repeats):
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        subprocess.run(command, check=True)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--tree", type=Path, action="append", default=[],
                        help="another source tree whose dice_core to run beside this one's")
    args = parser.parse_args()
    trees = [REPO, *args.tree]
    print(f"{dt.datetime.now(dt.timezone.utc):%Y-%m-%d %H:%M} UTC; load {os.getloadavg()[0]:.1f}; "
          f"{os.cpu_count()} cores; Python {sys.version.split()[0]}")
    bare = timed([sys.executable, "-c", "pass"], args.repeats)
    preamble = timed([sys.executable, "-c", "import pickle; from snakemake.logging import logger; "
                      "from snakemake.iocontainers import Snakemake"], args.repeats)
    print(f"python3 -c pass: {bare:.3f} s; the preamble's imports: {preamble:.3f} s (medians of {args.repeats})")
    results = {tree: {} for tree in trees}
    with tempfile.TemporaryDirectory() as folder:
        names = workflow(Path(folder), args.repeats)
        for tree in trees:
            results[tree] = run_tree(Path(folder), tree, names, args.repeats)
    print("\n| step's imports | " + " | ".join(f"{t} fixed cost (s) | job (s)" for t in trees) + " |")
    print("|---|" + "---:|---:|" * len(trees))
    for step in IMPORTS:
        cells = []
        for tree in trees:
            fixed, job = results[tree][step]
            cells += [f"{statistics.median(fixed):.2f} ({min(fixed):.2f}-{max(fixed):.2f})",
                      f"{statistics.median(job):.2f}"]
        print(f"| {step} | " + " | ".join(cells) + " |")
    print(f"\nload after: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
