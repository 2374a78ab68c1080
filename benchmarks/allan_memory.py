"""Peak memory and time of the Allan step (``allan_deviation``) against pixels and batches.

For a detector size and frame count given, in one run:

1. one baseline (H1H4, 2.4-pixel fringes at 2 degrees, the paper's noise): the ``large`` preset scaled to the
   detector as ``fit_memory.py`` scales it (``large_detector.size_overrides``: the beam's radius 1500 pixels
   a 1024 of side, the science area [2, n - 2] x [8, n - 2]), in plane waves, simulated with a fast sweep
   (``--sweep-frames`` frames a one-way sweep: short batches, so many of them), by the library
   (``dice_core.simulation``), into ``<workdir>/s<size>_..._large``; fitted once (``fringe_fit.fit_baseline``)
   and its ``metrology`` product and dark written there (reused by later runs of the same size);
2. one plain read pass of the baseline's files in a fresh process (float32 chunks summed over frames): what
   reading the cube costs, the yardstick of the times;
3. for each code tree given (``--tree name=path``: e.g. the base commit's ``git archive`` beside this tree),
   a fresh process that imports that tree's ``dice_core`` and does what the workflow's script does
   (``allan.allan_of_baseline`` then ``io.write_product``; a tree whose ``allan_of_baseline`` takes
   ``scratch`` is given the product's folder, as the script does). Each reports its wall time, its peak RSS
   (``VmHWM``) and its RSS once its imports are done (``VmRSS``): their difference is the step's own memory.
   This script samples the job's process tree every 20 ms (the job and the worker processes it forks when
   ``--workers`` is 2 and the baseline has two files or more): the peak of the sum of their RSS (shared pages
   counted in each process that maps them) and of their PSS (shared pages split between them: what the
   processes take together), and each worker's peak RSS. The job also times its phases from its log: the
   reading pass (the batches' fits) and what follows it (the groups' fits, the statistics, the write).

``--unused-maps N`` gives the job a copy of the metrology product with N more float64 maps that the step does
not use (a spherical-wave solution's product holds 10 more than a plane wave's: its modes, local
wavevectors, plane-wave departure, PRNU-free offsets): a step that reads the product whole holds them.

Until 2026-12-05 the bench was the simulation's defaults (the default preset's beam, a 300-pixel radius, its
levels, every pixel a science pixel; the same fringes, sweep and noise), in folders without ``_large``: its
envelope, of mean 1 over the detector, saturated a 2048x2048 detector's centre (324,110 pixels; the fit
failed). BENCHMARKS.md's rows at 512x512 and 1024x1024 before that date are of that bench. The same code on
both benches at those sizes: the same batches, the process tree's peaks (summed PSS and RSS) within 2%, the job's
own peak RSS within 5% (4.6% less at 1024x1024) (BENCHMARKS.md, "The Allan job at 2048x2048, measured").

Memory is reported in MiB (2^20 bytes; the fields named ``_mb``), as /proc gives it in KiB.

Printed: per tree, batches, time (and over the plain pass), peak RSS, the step's own memory and that per pixel
and per pixel and batch, the process tree's peaks and the phases' times; for each tree after the first, the
largest difference of its product from the first tree's (every variable, coordinate and attribute compared).
Every run's numbers are appended to ``<workdir>/allan_memory.json``, one line a run.

    git archive <base> dice_core | tar -x -C /tmp/dice-base
    python benchmarks/allan_memory.py --workdir /tmp/dice-allanmem --tree base=/tmp/dice-base --tree new=$PWD \\
        --size 512 --frames 8000
    python benchmarks/allan_memory.py --workdir /tmp/dice-allanmem --tree new=$PWD --size 1024 --frames 2000 \\
        --frames-per-file 1000 --workers 2
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from user_path import PROC_STATUS  # a script beside this one (its folder is first on sys.path)

REPO = Path(__file__).resolve().parents[1]
BASELINE = "H1H4"

#: What the job's process runs (argv: tree, manifest, metrology, dark, baseline, output, workers, pixels per
#: block or "default"): the workflow script's calls.
JOB = r"""
import inspect, json, logging, sys, time
tree, manifest, metrology, dark, baseline, output, workers, per_block, chunk_frames = sys.argv[1:10]
sys.path.insert(0, tree)
from pathlib import Path
import numpy as np
import xarray, netCDF4, scipy.sparse  # the workflow's imports, before the step is timed
import dice_core
from dice_core import allan, io
from dice_core.manifest import load_manifest

""" + PROC_STATUS + r"""
class Times(logging.Handler):  # when each log line was written: the phases of the job
    lines = []
    def emit(self, record):
        self.lines.append((time.perf_counter(), record.getMessage()))

logging.getLogger().addHandler(Times())
logging.getLogger().setLevel(logging.INFO)
base = status("VmRSS")
start = time.perf_counter()
manifest = load_manifest(manifest)
stream = io.FrameStream(manifest.baselines[baseline], manifest.detector, dtype="float32",
                        chunk_frames=chunk_frames if chunk_frames == "auto" else int(chunk_frames))
extra = {}
if "scratch" in inspect.signature(allan.allan_of_baseline).parameters:
    extra["scratch"] = Path(output).parent
    if per_block != "default":
        extra["pixels_per_block"] = int(per_block)
if hasattr(io, "open_product"):  # as the workflow's script: the products opened lazily
    with io.open_product(metrology) as solution, io.open_product(dark) as dark_product:
        product = allan.allan_of_baseline(stream, solution, dark=dark_product, detector=manifest.detector,
                                          workers=int(workers), **extra)
else:
    product = allan.allan_of_baseline(stream, io.read_product(metrology), dark=io.read_product(dark),
                                      detector=manifest.detector, workers=int(workers), **extra)
io.write_product(product, output, title="allan", inputs=[])
end = time.perf_counter()
def at(text):
    return next(t for t, line in Times.lines if text in line)
pass_start = at("batch fits over")
pass_end = next(t for t, line in Times.lines if t > pass_start and "batch fits over" not in line)
print(json.dumps({"seconds": end - start, "peak_mb": status("VmHWM"), "base_mb": base,
                  "batches": int(product.sizes["batch"]), "sizes": int(product.sizes["n_frames"]),
                  "pixels": int(np.isfinite(product["deviation"][0]).sum()),
                  "before_pass_s": pass_start - start, "pass_s": pass_end - pass_start,
                  "groups_s": at("group sizes fitted") - pass_end, "after_groups_s": end - at("group sizes fitted")}))
"""


def _tree(pid: int) -> list[int]:
    """``pid`` and its descendants (from /proc's children lists)."""
    found, todo = [], [pid]
    while todo:
        p = todo.pop()
        found.append(p)
        try:
            for task in os.listdir(f"/proc/{p}/task"):
                with open(f"/proc/{p}/task/{task}/children") as f:
                    todo += [int(c) for c in f.read().split()]
        except OSError:
            pass
    return found


def _memory(pid: int) -> tuple[float, float]:
    """RSS and PSS of a process, MiB (0 if it has ended)."""
    try:
        with open(f"/proc/{pid}/smaps_rollup") as f:
            fields = {line.split(":")[0]: int(line.split()[1]) for line in f if line.split()[-1] == "kB"}
        return fields["Rss"] / 1024, fields["Pss"] / 1024
    except (OSError, KeyError, ValueError):
        return 0.0, 0.0


def run_job(tree, manifest, metrology, dark, baseline, output, *, workers=1, pixels_per_block="default",
            chunk_frames="auto") -> dict:
    """The Allan step of the code ``tree`` in a fresh process: its report (seconds, peak and base RSS in MiB,
    batches, pixels)."""
    job = subprocess.Popen([sys.executable, "-c", JOB, str(Path(tree).resolve()), str(manifest), str(metrology),
                            str(dark), baseline, str(output), str(workers), str(pixels_per_block), str(chunk_frames)],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    peak_rss = peak_pss = 0.0
    workers_rss = {}
    while job.poll() is None:  # the process tree's memory, sampled
        tree_pids = _tree(job.pid)
        sampled = {p: _memory(p) for p in tree_pids}
        peak_rss = max(peak_rss, sum(r for r, _ in sampled.values()))
        peak_pss = max(peak_pss, sum(q for _, q in sampled.values()))
        for p in tree_pids[1:]:
            workers_rss[p] = max(workers_rss.get(p, 0.0), sampled[p][0])
        time.sleep(0.02)
    out, err = job.communicate()
    if job.returncode:
        raise RuntimeError(f"the job failed ({job.returncode}): {err[-3000:]}")
    report = json.loads(out.strip().splitlines()[-1])
    report.update(tree_peak_rss_mb=peak_rss, tree_peak_pss_mb=peak_pss,
                  worker_peak_rss_mb=sorted(workers_rss.values(), reverse=True))
    return report


PLAIN = r"""
import sys, time
sys.path.insert(0, sys.argv[1])
from dice_core import io
from dice_core.manifest import load_manifest
manifest = load_manifest(sys.argv[2])
stream = io.FrameStream(manifest.baselines["H1H4"], manifest.detector, chunk_frames="auto", dtype="float32")
start = time.perf_counter()
total = 0.0
for chunk in stream:
    total += float(chunk.frames.sum(dtype="float64"))
print(time.perf_counter() - start)
"""


def prepare(size: int, frames: int, sweep_frames: int, folder: Path, frames_per_file: int = 2000) -> None:
    """Simulate, fit and write the metrology product and dark of the bench (once per folder): the ``large``
    preset scaled to the size by ``large_detector.size_overrides`` (as ``fit_memory.py``), in plane waves."""
    import xarray as xr

    from dice_core import fringe_fit, fringes, io, simulation
    from dice_core.manifest import load_manifest

    from large_detector import PRESET, size_overrides  # the large preset scaled to the size, as there

    if (folder / "metrology.nc").exists():
        return
    overrides = {**size_overrides(size, size, frames), "name": "allan-memory", "frames_per_file": frames_per_file,
                 "dark.frames": 2, "flats.frames": 2, "stars.positions": 1, "stars.frames": 1,
                 "metrology.sweep_frames": sweep_frames, "metrology.spherical": False,
                 f"metrology.baselines.{BASELINE}.midpoint": [0.0, 0.0]}  # plane waves: no fiber tips
    cfg = simulation.load_preset(PRESET, overrides=overrides)
    manifest = load_manifest(simulation.simulate_dataset(cfg, folder / "raw"))
    truth = io.read_product(folder / "raw" / "truth.nc")
    stream = io.FrameStream(manifest.baselines[BASELINE], manifest.detector, dtype="float32")
    solution = fringe_fit.fit_baseline(stream, truth["bias"].values, detector=manifest.detector,
                                       flat=truth["sensitivity"].values, read_noise=truth["read_noise"].values)
    io.write_product(fringes.solution_dataset(solution, manifest.detector), folder / "metrology.nc", title="fit")
    dark = xr.Dataset({"dark": (("row", "col"), truth["bias"].values, {"units": "adu"}),
                       "noise": (("row", "col"), truth["read_noise"].values, {"units": "adu"})})
    io.write_product(dark, folder / "dark.nc", title="dark")


def add_unused_maps(source: Path, target: Path, n: int) -> None:
    """A copy of a metrology product with ``n`` float64 maps more, as a (unused, row, col) variable."""
    import numpy as np

    from dice_core import io

    product = io.read_product(source)
    shape = (n, product.sizes["row"], product.sizes["col"])
    product["unused_maps"] = (("unused", "row", "col"), np.random.default_rng(0).normal(size=shape), {"units": "1"})
    io.write_product(product, target, title="metrology product with unused maps")


def differences(one: Path, two: Path) -> dict:
    """Largest absolute difference of every variable of two products (NaN where they agree on NaN), and
    whether their dims, coordinates and attributes are the same."""
    import numpy as np
    import xarray as xr

    a, b = xr.load_dataset(one), xr.load_dataset(two)
    same = (set(a.data_vars) == set(b.data_vars) and all(a[v].dims == b[v].dims and a[v].attrs == b[v].attrs
                                                         for v in a.data_vars)
            and all(a[c].equals(b[c]) for c in a.coords) and set(a.coords) == set(b.coords)
            and {k: v for k, v in a.attrs.items() if k != "history"}
            == {k: v for k, v in b.attrs.items() if k != "history"})
    out = {}
    for name in a.data_vars:
        x, y = np.asarray(a[name].values, float), np.asarray(b[name].values, float)
        nan_same = bool(np.array_equal(np.isnan(x), np.isnan(y)))
        out[name] = float(np.nanmax(np.abs(x - y))) if nan_same and np.isfinite(x).any() else (0.0 if nan_same
                                                                                              else float("inf"))
    return {"same_metadata": bool(same), "max_difference": out}


def main(argv=None):
    from workflow_metrology import machine

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/dice-allanmem"))
    parser.add_argument("--tree", action="append", required=True, help="name=path of a code tree")
    parser.add_argument("--size", type=int, default=512, help="detector side, pixel")
    parser.add_argument("--frames", type=int, default=8000)
    parser.add_argument("--sweep-frames", type=int, default=60)
    parser.add_argument("--frames-per-file", type=int, default=2000,
                        help="the baseline's files (two workers need two files at least)")
    parser.add_argument("--unused-maps", type=int, default=0,
                        help="float64 maps added to the metrology product that the step does not use")
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--chunk-frames", default="auto", help='the stream\'s chunk_frames ("auto" or frames)')
    parser.add_argument("--pixels-per-block", default="default",
                        help="the Allan step's bands of pixels (a tree that has them; default: its own choice)")
    args = parser.parse_args(argv)
    per_file = "" if args.frames_per_file == 2000 else f"_p{args.frames_per_file}"
    folder = (args.workdir / f"s{args.size}_f{args.frames}_w{args.sweep_frames}{per_file}_large").resolve()
    folder.mkdir(parents=True, exist_ok=True)
    prepare(args.size, args.frames, args.sweep_frames, folder, args.frames_per_file)
    metrology = folder / "metrology.nc"
    if args.unused_maps:
        metrology = folder / f"metrology-unused{args.unused_maps}.nc"
        if not metrology.exists():
            add_unused_maps(folder / "metrology.nc", metrology, args.unused_maps)
    results = {"machine": machine(), "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
               "load": os.getloadavg(), "size": args.size, "frames": args.frames, "workers": args.workers,
               "pixels_per_block": args.pixels_per_block, "unused_maps": args.unused_maps,
               "chunk_frames": args.chunk_frames,
               "metrology_mb": metrology.stat().st_size / 2**20}
    plain = subprocess.run([sys.executable, "-c", PLAIN, str(REPO), str(folder / "raw" / "dataset.yaml")],
                           check=True, capture_output=True, text=True)
    results["plain_pass_s"] = float(plain.stdout)
    products = {}
    for spec in args.tree:
        name, tree = spec.split("=", 1)
        output = folder / f"allan-{name}-{args.pixels_per_block}-c{args.chunk_frames}.nc"
        run = run_job(tree, folder / "raw" / "dataset.yaml", metrology, folder / "dark.nc", BASELINE,
                      output, workers=args.workers, pixels_per_block=args.pixels_per_block,
                      chunk_frames=args.chunk_frames)
        own = run["peak_mb"] - run["base_mb"]
        run.update(own_mb=own, bytes_per_pixel=own * 2**20 / args.size**2,
                   bytes_per_pixel_batch=own * 2**20 / args.size**2 / run["batches"],
                   over_plain=run["seconds"] / results["plain_pass_s"])
        if products:
            run["against_" + next(iter(products))] = differences(next(iter(products.values())), output)
        products[name] = output
        results[name] = run
        print(name, json.dumps(run, indent=1))
    print(f"plain pass {results['plain_pass_s']:.1f} s; load {results['load']}; {results['machine']}")
    with open(args.workdir / "allan_memory.json", "a") as f:  # one line a run
        f.write(json.dumps(results) + "\n")


if __name__ == "__main__":
    sys.path[:0] = [str(REPO), str(REPO / "benchmarks")]
    main()
