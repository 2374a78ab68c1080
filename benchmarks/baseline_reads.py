"""Reads, time and peak memory of one metrology baseline's jobs, on the path users take, old code beside new.

For each size given (rows x cols x frames of one baseline), in one run of this script:

1. the dataset is simulated once (cached in ``--workdir``): a dark, two flats and the baseline, in files of
   ``--frames-per-file`` frames (uint16), the paper preset's noise, the fringe sweep of
   ``benchmarks/workflow_metrology.py``;
2. one plain read pass of the baseline's files in a fresh process (float32 chunks summed over frames,
   imports excluded): the unit the jobs' times are quoted in;
3. for each code tree given (``--tree NAME=PATH``: a checkout of the repository, e.g. the base commit's
   ``git archive`` beside this worktree) and each way of fitting (``single``: ``fit_fringes``; ``split``:
   ``metrology.split: true``, its ``fit_start``, ``fit_part``, ``fit_reduce`` and ``fit_finish`` jobs), the
   README's command ``python -m snakemake --cores C --config dataset=<manifest> results=<dir> ...`` for the
   baseline's ``metrology/`` and ``allan/`` products, from the tree's own Snakefile and ``dice_core``;
4. the products of the trees compared, for each way: every variable's data, every coordinate and every
   attribute but those that name the code (``code_version``, ``source``, ``history``).

Each job's process records, at its exit, the bytes it read from FITS files (every ``open`` of a ``.fits``
file for reading is counted: the streams, the headers, any hash; page cache or disk alike) and its peak RSS
(``VmHWM``), through a ``sitecustomize`` hook this script puts first on ``PYTHONPATH``; forked worker
processes are not counted, so the reads are measured with ``--cores 1`` (each job reads its lanes itself).
``reads`` is a job's FITS bytes over the baseline's files' bytes (a job reads no other FITS file).
Job times are Snakemake's ``benchmark:`` files (the whole job: start, imports, inputs, the step,
the product).

    git -C <repo> archive <base commit> | tar -x -C /tmp/dice-old
    python benchmarks/baseline_reads.py --workdir /tmp/dice-reads --tree old=/tmp/dice-old --tree new=. \\
        80x84x20000 256x256x4000

Prints one Markdown table per size and writes every number to ``<workdir>/reads.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections import defaultdict
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))
from user_path import benchmark_record, machine, plain_read, snakemake  # noqa: E402  (scripts beside this one)
from workflow_metrology import BASELINE  # noqa: E402

#: Written into the workdir as ``sitecustomize.py``: every Python process started with it on the path
#: (the jobs' scripts) appends its reads and peak memory to $DICE_BENCH_IO_LOG at exit.
HOOK = '''
import atexit, builtins, io, json, os, sys, time
_log, _pid, _start, _fits = os.environ.get("DICE_BENCH_IO_LOG"), os.getpid(), time.time(), [0]
_open = builtins.open


class _Counted:
    # a FITS file opened for reading: the bytes read from it counted, everything else its own
    def __init__(self, f):
        self._f = f

    def __getattr__(self, name):
        return getattr(self._f, name)

    def read(self, *args):
        data = self._f.read(*args)
        _fits[0] += len(data or b"")
        return data

    def readinto(self, buffer):
        n = self._f.readinto(buffer)
        _fits[0] += n or 0
        return n

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return self._f.__exit__(*exc)


def _counted_open(file, mode="r", *args, **kwargs):
    f = _open(file, mode, *args, **kwargs)
    if isinstance(file, (str, os.PathLike)) and os.fspath(file).endswith(".fits") and "r" in mode:
        return _Counted(f)
    return f


def _record():
    if os.getpid() != _pid:  # a forked worker: not this process
        return
    proc = dict(line.split(": ") for line in _open("/proc/self/io").read().splitlines())
    # VmHWM: the peak RSS of this program (ru_maxrss would keep the Snakemake process's across exec)
    hwm = next(int(line.split()[1]) for line in _open("/proc/self/status") if line.startswith("VmHWM"))
    with _open(_log, "a") as f:
        f.write(json.dumps({"argv": sys.argv, "rchar": int(proc["rchar"]), "fits_bytes": _fits[0],
                            "max_rss_mb": hwm / 1024, "seconds": time.time() - _start}) + "\\n")


if _log:
    builtins.open = io.open = _counted_open
    atexit.register(_record)
'''

STEPS = ("fit_fringes", "fit_start", "fit_part", "fit_reduce", "fit_finish", "allan_deviation")


def config(rows, cols, frames, frames_per_file, sweep_frames=1000):
    from dice_core import simulation

    return simulation.SimulationConfig.from_dict({
        "name": f"reads-{rows}x{cols}x{frames}-s{sweep_frames}", "seed": 20150926, "frames_per_file": frames_per_file,
        "detector": {"shape": [rows, cols], "science_rows": [2, rows - 1], "science_cols": [10, cols - 1],
                     "gain": 10.0, "read_noise": 4.0},
        "dark": {"frames": 100}, "flats": {"frames": 100, "level": 20000.0},
        "stars": {"positions": 1, "frames": 1},
        "metrology": {"frames": frames, "sweep_frames": sweep_frames, "mean_level": 10000.0, "amplitude": 6000.0,
                      "baselines": {BASELINE: {"period": 2.4, "angle_deg": 2.0}}, "pairs": {}},
    })


def prepare(rows, cols, frames, frames_per_file, sweep_frames, data: Path) -> Path:
    """The dataset's manifest, simulated into ``data`` unless already there."""
    from dice_core import simulation

    manifest = data / "dataset.yaml"
    if not manifest.exists():
        start = time.perf_counter()
        simulation.simulate_dataset(config(rows, cols, frames, frames_per_file, sweep_frames), data)
        print(f"simulated {rows}x{cols}x{frames} in {time.perf_counter() - start:.0f} s", file=sys.stderr)
    return manifest


def plain_pass(manifest) -> float:
    return plain_read(manifest, BASELINE)["seconds"]


def run(tree: Path, manifest: Path, results: Path, name: str, *, split: bool, cores: int, hook: Path, log: Path):
    """The README's command for the baseline's two products, from ``tree``; the jobs' records."""
    targets = [f"{results}/{name}/metrology/{BASELINE}.nc", f"{results}/{name}/allan/{BASELINE}.nc"]
    log.unlink(missing_ok=True)
    env = {**os.environ, "PYTHONPATH": f"{hook}:{tree}", "DICE_BENCH_IO_LOG": str(log)}
    wall = snakemake("--snakefile", str(tree / "Snakefile"), "--directory", str(tree),
                     "--configfile", str(hook.parent / f"split_{str(split).lower()}.yaml"),
                     "--config", f"dataset={manifest}", f"results={results}", "--forceall", "--", *targets,
                     cores=cores, tree=tree, env=env).wall_s
    jobs = defaultdict(list)
    for line in log.read_text().splitlines():
        record = json.loads(line)
        script = Path(record["argv"][0]).name if record["argv"] else ""
        step = next((s for s in STEPS if script.endswith(f".{s}.py") or script == f"{s}.py"), None)
        if step is not None:
            jobs[step].append(record)
    bench = results / name / "benchmarks"
    for step in jobs:
        seconds = [benchmark_record(path)["s"] for path in sorted(bench.glob(f"{step}_*.tsv"))]
        for record in jobs[step]:
            record["benchmark_s"] = seconds
    return wall, dict(jobs)


def compare(first: Path, second: Path) -> list[str]:
    """Differences between two products: data, coordinates and attributes but those naming the code."""
    import xarray as xr

    skip = {"code_version", "source", "history"}
    with xr.open_dataset(first) as a, xr.open_dataset(second) as b:
        a.load(), b.load()
        problems = [f"attribute {k}" for k in sorted(set(a.attrs) | set(b.attrs))
                    if k not in skip | {"inputs"} and str(a.attrs.get(k)) != str(b.attrs.get(k))]
        if _inputs(a) != _inputs(b):
            problems.append("attribute inputs")
        for name in sorted(set(a.variables) | set(b.variables)):
            if name not in a.variables or name not in b.variables:
                problems.append(f"variable {name} in one only")
            elif not a[name].variable.identical(b[name].variable):
                problems.append(f"variable {name}")
    return problems


def _inputs(ds) -> list:
    """A product's ``inputs`` records, but the checksums of other products (netCDF files, whose bytes hold
    the time and code they were written with): the raw files' checksums compared with their paths."""
    return [{**r, "sha256": None} if r["path"].endswith(".nc") else r for r in json.loads(ds.attrs["inputs"])]


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sizes", nargs="+", help="ROWSxCOLSxFRAMES")
    parser.add_argument("--workdir", type=Path, required=True)
    parser.add_argument("--tree", action="append", required=True, help="NAME=PATH of a checkout")
    parser.add_argument("--frames-per-file", type=int, default=2000)
    parser.add_argument("--cores", type=int, default=1)
    parser.add_argument("--ways", default="single,split")
    parser.add_argument("--sweep-frames", type=int, default=1000,
                        help="the simulated sweep's pace: fewer frames a fringe period, more Allan batches")
    args = parser.parse_args()
    workdir = args.workdir.resolve()
    hook = workdir / "hook"
    hook.mkdir(parents=True, exist_ok=True)
    (hook / "sitecustomize.py").write_text(HOOK)
    for split in ("true", "false"):  # merged over the tree's config/config.yaml
        (workdir / f"split_{split}.yaml").write_text(f"metrology:\n  split: {split}\n")
    trees = dict(item.split("=", 1) for item in args.tree)
    out = {"machine": machine(), "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "sizes": {}}
    for size in args.sizes:
        rows, cols, frames = map(int, size.split("x"))
        manifest = prepare(rows, cols, frames, args.frames_per_file, args.sweep_frames,
                           workdir / "data" / f"{size}-s{args.sweep_frames}")
        from dice_core.manifest import load_manifest

        files = load_manifest(manifest).baselines[BASELINE].files
        cube_bytes = sum(Path(f).stat().st_size for f in files)
        entry = {"cube_bytes": cube_bytes, "load_before": os.getloadavg(), "plain_s": [plain_pass(manifest)]}
        for way in args.ways.split(","):
            for tree_name, tree in trees.items():
                results = workdir / "results" / f"{size}-s{args.sweep_frames}" / tree_name / way
                wall, jobs = run(Path(tree).resolve(), manifest, results, load_manifest(manifest).name,
                                 split=way == "split", cores=args.cores, hook=hook, log=workdir / "io.log")
                entry[f"{tree_name}/{way}"] = {"wall_s": wall, "jobs": jobs}
            entry["plain_s"].append(plain_pass(manifest))
            names = list(trees)
            name = load_manifest(manifest).name
            for product in (f"metrology/{BASELINE}.nc", f"allan/{BASELINE}.nc"):
                paths = [workdir / "results" / f"{size}-s{args.sweep_frames}" / t / way / name / product
                         for t in names]
                entry[f"compare/{way}/{product}"] = compare(*paths[:2]) if len(paths) > 1 else []
        entry["load_after"] = os.getloadavg()
        logs = sorted((workdir / "results" / f"{size}-s{args.sweep_frames}").glob("*/*/*/logs/allan_deviation_*.log"))
        entry["allan_batches"] = next((line.split(": ", 2)[-1] for line in logs[0].read_text().splitlines()
                                       if " batches of " in line), None) if logs else None
        out["sizes"][size] = entry
        (workdir / "reads.json").write_text(json.dumps(out, indent=1))
        print(table(size, entry, trees))
    print(f"\n{out['machine']}; {out['date']}")


def table(size, entry, trees) -> str:
    plain = min(entry["plain_s"])
    lines = [f"\n{size}: baseline {entry['cube_bytes'] / 1e9:.2f} GB, plain pass {plain:.2f} s "
             f"({', '.join(f'{s:.2f}' for s in entry['plain_s'])}), load {entry['load_before'][0]:.1f}; Allan: "
             f"{entry.get('allan_batches')}",
             "", "| code | way | step | jobs | reads of the baseline (sum) | peak RSS (MB, max) | job time (s, sum) "
                 "| job time / plain pass |", "|---|---|---|---:|---:|---:|---:|---:|"]
    for key, run_ in entry.items():
        if "/" not in key or key.startswith("compare") or not isinstance(run_, dict):
            continue
        tree, way = key.split("/")
        total_reads = 0.0
        for step, records in run_["jobs"].items():
            reads = sum(r["fits_bytes"] for r in records) / entry["cube_bytes"]
            total_reads += reads
            seconds = sum(records[0]["benchmark_s"])
            lines.append(f"| {tree} | {way} | `{step}` | {len(records)} | {reads:.2f} | "
                         f"{max(r['max_rss_mb'] for r in records):.0f} | {seconds:.1f} | {seconds / plain:.2f} |")
        lines.append(f"| {tree} | {way} | all | | **{total_reads:.2f}** | | | |")
    for key, problems in entry.items():
        if key.startswith("compare"):
            lines.append(f"\n{key}: {'identical' if not problems else 'DIFFER: ' + ', '.join(problems)}")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
