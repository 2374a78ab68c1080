"""Peak memory of a split fringe fit's ``fit_reduce`` and ``fit_finish`` jobs against the detector's pixels.

For each detector size given (rows x cols, or one number for a square), in one run:

1. the ``large`` preset's bench (spherical-wave fringes, the paper's noise) simulated with that detector and
   few frames (``--frames``, in two files), by the library (``dice_core.simulation``), into ``<workdir>``;
2. the split fit run in this process as the workflow's jobs run it (:func:`dice_core.fringe_fit.start_fit`,
   each pass's two ``part_dataset`` products, ``reduce_dataset``), every state and part written to netCDF;
3. for each code tree given (``--tree name=path``: e.g. the base commit's ``git archive`` beside this
   tree), a fresh process per job that imports that tree's ``dice_core`` and does what the workflow's
   script does: ``fit_reduce`` of pass 1 and of the last pass (the state and the parts read, the state
   after the pass written) and ``fit_finish`` (the state its last reduction wrote read, the solution with
   the bench's geometry and a read-noise map, the metrology product written). Each reports its peak RSS
   (``VmHWM``) and its RSS once its imports are done (``VmRSS``): their difference is the step's own
   memory.

Printed: per size, tree and job, peak RSS, the step's own memory and that per detector pixel, and, for each
tree after the first, the largest difference of its metrology product from the first tree's (pixel for
offsets): of ``fit_finish`` from the same state, or with ``--compare`` of the whole fit (``fit_baseline``,
the single job's path, whose product is the split fit's bit for bit) run by each tree from the raw files.
Every number goes to ``<workdir>/fit_memory.json``; the simulated files stay (``--drop-raw`` removes them).

    git archive main | tar -x -C /tmp/dice-main
    python benchmarks/fit_memory.py --workdir /tmp/dice-fitmem --tree main=/tmp/dice-main --tree new=$PWD \\
        --compare 256 512 1024
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

from user_path import PROC_STATUS  # a script beside this one (its folder is first on sys.path)

REPO = Path(__file__).resolve().parents[1]
BASELINE = "H1H4"

#: What a job's process runs (argv: tree, job, workdir of the size, output): the workflow script's calls.
JOB = r"""
import json, sys
tree, job, folder, output, last_state = sys.argv[1:6]
sys.path.insert(0, tree)
from pathlib import Path
import numpy as np
import xarray, netCDF4, scipy.linalg  # the workflow's imports, before the baseline is taken
import dice_core
from dice_core import fringe_fit, fringes, io
from dice_core.geometry import BaselineGeometry
from dice_core.manifest import load_manifest

""" + PROC_STATUS + r"""
folder = Path(folder)
base = status("VmRSS")
def geometry_of(manifest):
    return BaselineGeometry.of_baseline(manifest.geometry, "H1H4", tip_sigma=1e-3,
                                        wavelength=manifest.baseline_wavelength("H1H4"))

if job == "single":  # the whole fit from the raw files (the single job's path, bit for bit the split fit's)
    manifest = load_manifest(folder / "raw" / "dataset.yaml")
    truth = io.read_product(folder / "raw" / "truth.nc")
    stream = fringe_fit.metrology_stream(manifest.baselines["H1H4"], manifest.detector)
    solution = fringe_fit.fit_baseline(stream, truth["bias"].values, detector=manifest.detector,
                                       flat=truth["sensitivity"].values, read_noise=truth["read_noise"].values,
                                       geometry=geometry_of(manifest), label="H1H4")
    product = fringes.metrology_product(solution, manifest.detector, baseline="H1H4", geometry=geometry_of(manifest))
    io.write_product(product, output, title="metrology")
elif job.startswith("reduce"):
    n = int(job.split("_")[1])
    state = io.read_product(folder / f"state_{n - 1}.nc")
    parts = sorted(folder.glob(f"part_{n}_*.nc"))
    product = fringe_fit.reduce_dataset(state, parts)
    io.write_product(product, output, title="state")
else:  # as workflow/scripts/fit_finish.py: the dark's noise only, the state dropped before the product
    manifest = load_manifest(folder / "raw" / "dataset.yaml")
    read_noise = io.read_product(folder / "dark.nc")["noise"].values
    geometry = geometry_of(manifest)
    state = fringe_fit.state_from_dataset(io.read_product(last_state))
    solution = fringe_fit.finish_fit(state, detector=manifest.detector, read_noise=read_noise, geometry=geometry)
    del state, read_noise
    product = fringes.metrology_product(solution, manifest.detector, baseline="H1H4", geometry=geometry)
    io.write_product(product, output, title="metrology")
print(json.dumps({"base_mb": base, "peak_mb": status("VmHWM"), "file": dice_core.__file__}))
"""


def prepare(rows: int, cols: int, frames: int, folder: Path) -> int:
    """Simulate the size and run its split fit, writing ``state_<n>.nc``, ``part_<n>_<i>.nc``,
    ``state_last.nc`` and ``dark.nc`` in ``folder``; the pass the fit stopped at."""
    from dice_core import fringe_fit, io, simulation
    from dice_core.manifest import load_manifest

    from large_detector import PRESET, size_overrides  # the large preset scaled to the size, as there

    overrides = {**size_overrides(rows, cols, frames), "frames_per_file": frames // 2, "dark.frames": 2,
                 "flats.frames": 2, "stars.positions": 1, "stars.frames": 1}
    cfg = simulation.load_preset(PRESET, overrides=overrides)
    path = simulation.simulate_dataset(cfg, folder / "raw")
    manifest = load_manifest(path)
    truth = io.read_product(folder / "raw" / "truth.nc")
    dark = truth[["bias", "read_noise"]].rename(bias="dark", read_noise="noise")
    io.write_product(dark, folder / "dark.nc", title="dark")
    stream = fringe_fit.metrology_stream(manifest.baselines[BASELINE], manifest.detector)
    state = fringe_fit.start_fit(stream, truth["bias"].values, detector=manifest.detector,
                                 flat=truth["sensitivity"].values, label=BASELINE)
    del truth
    io.write_product(fringe_fit.state_dataset(state), folder / "state_0.nc", title="state")
    n_pass = 0
    while True:
        n_pass += 1
        with io.xr.open_dataset(folder / f"state_{n_pass - 1}.nc") as ds:
            for part in range(2):
                io.write_product(fringe_fit.part_dataset(stream, ds, part=part, parts=2),
                                 folder / f"part_{n_pass}_{part}.nc", title="part")
        reduced = fringe_fit.reduce_dataset(io.read_product(folder / f"state_{n_pass - 1}.nc"),
                                            sorted(folder.glob(f"part_{n_pass}_*.nc")))
        io.write_product(reduced, folder / f"state_{n_pass}.nc", title="state")
        if reduced.attrs["fit_done"]:
            shutil.copy(folder / f"state_{n_pass}.nc", folder / "state_last.nc")
            return n_pass


def run_job(tree: Path, job: str, folder: Path, output: Path, last_state: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": str(tree), "OPENBLAS_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, "-c", JOB, str(tree), job, str(folder), str(output), str(last_state)],
                          env=env, capture_output=True, text=True)
    if done.returncode:
        sys.exit(f"{job} with {tree} failed:\n{done.stderr[-4000:]}")
    result = json.loads(done.stdout.strip().splitlines()[-1])
    if not result["file"].startswith(str(tree)):
        sys.exit(f"{job}: imported {result['file']}, not the tree {tree}")
    return result


def max_difference(one: Path, two: Path) -> dict:
    """The largest absolute difference of each float variable of two products (NaN where one only is NaN)."""
    import numpy as np

    from dice_core.io import read_product

    a, b = read_product(one), read_product(two)
    out = {}
    for name in a.data_vars:
        x, y = a[name].values, b[name].values
        if x.dtype.kind != "f" or x.shape != y.shape:
            out[name] = None if np.array_equal(x, y) else "differs"
            continue
        if not np.array_equal(np.isnan(x), np.isnan(y)):
            out[name] = "NaN differs"
            continue
        out[name] = float(np.nanmax(np.abs(x - y))) if np.isfinite(x).any() else 0.0
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("sizes", nargs="+", help="rows x cols (or one number for a square)")
    parser.add_argument("--workdir", type=Path, required=True)
    parser.add_argument("--tree", action="append", required=True, help="name=path of a tree with dice_core")
    parser.add_argument("--frames", type=int, default=400)
    parser.add_argument("--compare", action="store_true",
                        help="also fit the whole baseline with each tree, and compare those products (not only "
                             "the products of fit_finish from one state)")
    parser.add_argument("--drop-raw", action="store_true", help="remove the simulated files after a size")
    args = parser.parse_args()
    trees = dict(t.split("=", 1) for t in args.tree)
    results = []
    for size in args.sizes:
        rows, cols = (int(v) for v in (size.split("x") if "x" in size else (size, size)))
        folder = args.workdir / f"{rows}x{cols}x{args.frames}"
        if not (folder / "state_last.nc").exists():
            folder.mkdir(parents=True, exist_ok=True)
            prepare(rows, cols, args.frames, folder)
        last = max(int(p.stem.split("_")[1]) for p in folder.glob("state_*.nc") if p.stem != "state_last")
        products = {}
        for name, tree in trees.items():
            for job in ("reduce_1", f"reduce_{last}", "finish", *(["single"] if args.compare else [])):
                output = folder / f"out_{name}_{job}.nc"
                # fit_finish reads the state the tree's own last reduction wrote
                measured = run_job(Path(tree).resolve(), job, folder, output,
                                   folder / f"out_{name}_reduce_{last}.nc")
                own = measured["peak_mb"] - measured["base_mb"]
                row = {"size": f"{rows}x{cols}", "frames": args.frames, "tree": name, "job": job,
                       "peak_mb": round(measured["peak_mb"], 1), "own_mb": round(own, 1),
                       "bytes_per_pixel": round(own * 2**20 / (rows * cols))}
                results.append(row)
                print(json.dumps(row), flush=True)
                if job == ("single" if args.compare else "finish"):
                    products[name] = output
        first = next(iter(products))
        for name in list(products)[1:]:
            diff = max_difference(products[first], products[name])
            print(json.dumps({"size": f"{rows}x{cols}", "against": first, "tree": name, "max_abs": diff}), flush=True)
            results.append({"size": f"{rows}x{cols}", "against": first, "tree": name, "max_abs": diff})
        if args.drop_raw:
            shutil.rmtree(folder / "raw")
    (args.workdir / "fit_memory.json").write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
