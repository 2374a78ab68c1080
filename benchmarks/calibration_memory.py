"""Peak memory and time of the calibration steps against the detector's size and the chunk's.

For each detector side given (square, the science area a frame less a margin of 4 and 8 pixels), in one run:

1. a small dataset written by this script (not the simulator, whose metrology truth would not fit at
   4096x4096) into ``<workdir>/s<side>_f<frames>``: a dark and two flats of ``--frames`` frames each
   (uint16 FITS cubes), with a column structure in the bias, hot pixels, a dead column and dead pixels,
   a vignetted illumination, and pixels that saturate in some of their samples (kept between runs of the
   same size and frames);
2. for each code tree given (``--tree name=path``: e.g. the base commit's ``git archive`` beside this
   tree), each step in a fresh process that imports that tree's ``dice_core`` and does what the workflow's
   script does (its library calls, ``io.FrameStream`` with the configuration's ``chunk_frames``, and
   ``io.write_product``): ``measure_dark``, ``measure_prnu`` (a process a flat), ``select_reference_prnu``,
   ``compare_prnu`` and, with ``--bad-pixels``, ``find_bad_pixels`` (its 5x5 median filters take about
   a minute a million pixels). Each reports its wall time, its peak RSS (``VmHWM``) and its RSS once its
   imports are done (``VmRSS``): their difference is the step's own memory.

Printed: a line per tree, step and chunk size (time, peak RSS, own memory, chunk frames and samples); for
each tree after the first (or each, with ``--compare-with``: against the products of an earlier run's tree),
whether each product equals the first tree's (every variable bit for bit, NaN
where NaN, its coordinates and attributes but the history and the write's date). Every run's numbers are
appended to ``<workdir>/calibration_memory.json``, one line a run. ``--drop`` removes a size's folder
after it (4096x4096 x 12 frames is 0.4 GB a cube).

    git archive <base> dice_core | tar -x -C /tmp/dice-calbase
    python benchmarks/calibration_memory.py --workdir /tmp/dice-calmem --tree base=/tmp/dice-calbase \\
        --tree new=$PWD --sizes 1024 2048 4096 --chunk-frames auto 4
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
FLATS = ("fiber_a", "fiber_b")
#: The steps in the workflow's order, a job each (one a flat for measure_prnu).
STEPS = ("measure_dark", *(f"measure_prnu_{flat}" for flat in FLATS), "select_reference_prnu", "compare_prnu",
         "find_bad_pixels")

#: What a step's process runs (argv: tree, folder, step, chunk_frames, output folder): the workflow
#: scripts' library calls (workflow/scripts/<step>.py), the manifest replaced by the bench's own detector
#: and acquisitions.
JOB = r"""
import json, sys, time
tree, folder, step, chunk_frames, out = sys.argv[1:6]
sys.path.insert(0, tree)
from pathlib import Path
import numpy as np
import xarray, netCDF4, astropy.io.fits  # the workflow's imports, before the step is timed
import dice_core
from dice_core import calibration, io
from dice_core.manifest import Acquisition, Detector

""" + PROC_STATUS + r"""
bench = json.loads(Path(folder, "bench.json").read_text())
detector = Detector(**{k: tuple(v) if isinstance(v, list) else v for k, v in bench["detector"].items()})
acquisition = {name: Acquisition(name, (Path(folder, f"{name}.fits"),)) for name in ["dark", *bench["flats"]]}
chunk_frames = chunk_frames if chunk_frames == "auto" else int(chunk_frames)
config = {"chunk_frames": chunk_frames, "prnu": {"gradient_degree": 1}}
out = Path(out)
base = status("VmRSS")
start = time.perf_counter()
if step == "measure_dark":
    stream = io.FrameStream(acquisition["dark"], detector, chunk_frames=chunk_frames, min_frames=2,
                            purpose="a temporal noise map")
    maps = calibration.dark_maps(stream, detector, n_frames=stream.n_frames)
    io.write_product(maps, out / "dark.nc", title="dark maps", config=config, inputs=[])
elif step.startswith("measure_prnu_"):
    flat = step[len("measure_prnu_"):]
    dark = io.read_product(out / "dark.nc")
    stream = io.FrameStream(acquisition[flat], detector, chunk_frames=chunk_frames, min_frames=2,
                            purpose="a PRNU map with its noise")
    prnu = calibration.prnu_map(stream, dark["dark"].values, dark_noise=dark["noise"].values,
                                detector=detector, gradient_degree=1, n_frames=stream.n_frames,
                                label=f"flat {flat}")
    prnu.attrs["flat"] = flat
    io.write_product(prnu, out / f"prnu_{flat}.nc", title=f"PRNU of flat {flat}", config=config, inputs=[])
elif step == "select_reference_prnu":
    prnu = io.read_product(out / f"prnu_{bench['flats'][0]}.nc")
    prnu.attrs = {"flat": bench["flats"][0]}
    io.write_product(prnu, out / "prnu.nc", title="reference PRNU", config=config, inputs=[])
elif step == "compare_prnu":
    reference, other = (io.read_product(out / f"prnu_{flat}.nc") for flat in bench["flats"])
    diff = calibration.prnu_difference(reference, other, detector=detector)
    diff.attrs = {"reference_flat": reference.attrs["flat"], "other_flat": other.attrs["flat"]}
    io.write_product(diff, out / "prnu_difference.nc", title="PRNU difference", config=config, inputs=[])
elif step == "find_bad_pixels":
    mask = calibration.bad_pixel_mask(io.read_product(out / "dark.nc"), io.read_product(out / "prnu.nc")["prnu"].values,
                                      detector=detector)
    io.write_product(mask, out / "bad_pixels.nc", title="bad-pixel mask", config=config, inputs=[])
print(json.dumps({"seconds": time.perf_counter() - start, "peak_mb": status("VmHWM"), "base_mb": base}))
"""


def bench_detector(side: int) -> dict:
    """The bench's detector: ``side`` x ``side``, the science area inside a margin of 4 rows and 8 columns."""
    return {"shape": [side, side], "science_rows": [4, side - 4], "science_cols": [8, side - 8], "gain": 10.0,
            "saturation": 60000.0, "read_noise": 4.0}


def prepare(side: int, frames: int, folder: Path) -> None:
    """Write the dark and the flats of the bench (once per folder): uint16 cubes, a frame at a time.

    Dark: a bias of 1000 adu with a column structure (10 adu rms), 4 adu of read noise, hot pixels (one in
    10,000: 3000 adu more; one in 50,000 at the saturation). Flats: the dark's bias plus 20,000 adu times a
    PRNU of 2e-3 rms, a gradient and a vignetting, a dead column and dead pixels (5% of the light); photon
    noise (gain 10 e-/adu) and read noise; pixels one in 20,000 at the saturation level, so that about half
    their samples saturate.
    """
    import numpy as np

    from dice_core import io

    if (folder / "bench.json").exists():
        return
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(side)
    detector = bench_detector(side)
    shape = (side, side)
    bias = (1000 + 10 * rng.standard_normal(side))[None, :] + rng.standard_normal(shape)
    hot = rng.random(shape) < 1e-4
    bias[hot] += 3000
    bias[rng.random(shape) < 2e-5] = detector["saturation"]
    rows, cols = np.indices(shape) / (side / 2) - 1
    light = 20000 * (1 + 2e-3 * rng.standard_normal(shape)) * (1 - 0.02 * (rows**2 + cols**2) + 0.05 * cols)
    light[:, side // 3] *= 0.05
    light[rng.random(shape) < 1e-4] *= 0.05
    light[rng.random(shape) < 5e-5] = detector["saturation"] - bias.mean()

    def cube(mean):
        sigma = np.sqrt(np.maximum(mean - bias, 0) / detector["gain"] + detector["read_noise"]**2)
        for _ in range(frames):
            yield (mean + sigma * rng.standard_normal(shape))[None]

    io.write_cube(folder / "dark.fits", cube(bias), shape=shape, n_frames=frames)
    for n, flat in enumerate(FLATS):
        io.write_cube(folder / f"{flat}.fits", cube(bias + light * (1 + 0.05 * n)), shape=shape, n_frames=frames)
    (folder / "bench.json").write_text(json.dumps({"detector": detector, "flats": list(FLATS), "frames": frames}))


def run_step(tree, folder, step, chunk_frames, out) -> dict:
    """One step of the code ``tree`` in a fresh process: its report (seconds, peak and base RSS in MiB)."""
    job = subprocess.run([sys.executable, "-c", JOB, str(Path(tree).resolve()), str(folder), step, str(chunk_frames),
                          str(out)], check=True, capture_output=True, text=True)
    return json.loads(job.stdout.strip().splitlines()[-1])


def identical(one: Path, two: Path) -> bool:
    """Whether two products hold the same variables bit for bit (NaN where NaN), the same coordinates and
    attributes (the global ones but ``history``, which dates the write)."""
    import numpy as np
    import xarray as xr

    def same_attrs(x, y):
        return x.keys() == y.keys() and all(np.array_equal(x[k], y[k]) for k in x)

    a, b = xr.load_dataset(one), xr.load_dataset(two)
    if set(a.variables) != set(b.variables):
        return False
    for name in a.variables:
        x, y = a[name], b[name]
        if x.dims != y.dims or not same_attrs(x.attrs, y.attrs) or x.dtype != y.dtype:
            return False
        if not np.array_equal(x.values, y.values, equal_nan=x.dtype.kind == "f"):
            return False
    return same_attrs({k: v for k, v in a.attrs.items() if k != "history"},
                      {k: v for k, v in b.attrs.items() if k != "history"})


def main(argv=None):
    from workflow_metrology import machine

    from dice_core.io import auto_chunk_frames

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/dice-calmem"))
    parser.add_argument("--tree", action="append", required=True, help="name=path of a code tree")
    parser.add_argument("--sizes", type=int, nargs="+", default=[1024, 2048, 4096], help="detector sides, pixel")
    parser.add_argument("--frames", type=int, default=12, help="frames of the dark and of each flat")
    parser.add_argument("--chunk-frames", nargs="+", default=["auto"],
                        help='chunk_frames settings to run ("auto" or integers)')
    parser.add_argument("--bad-pixels", action="store_true", help="also run find_bad_pixels (slow)")
    parser.add_argument("--compare-with", metavar="NAME",
                        help="compare the products with those a tree NAME made in an earlier run (not run again)")
    parser.add_argument("--drop", action="store_true", help="remove each size's folder after it")
    args = parser.parse_args(argv)
    steps = STEPS if args.bad_pixels else STEPS[:-1]
    for side in args.sizes:
        folder = (args.workdir / f"s{side}_f{args.frames}").resolve()
        prepare(side, args.frames, folder)
        for chunk_frames in args.chunk_frames:
            frames = min(args.frames, auto_chunk_frames((side, side)) if chunk_frames == "auto" else int(chunk_frames))
            results = {"machine": machine(), "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                       "load": os.getloadavg(), "side": side, "frames": args.frames, "chunk_frames": chunk_frames,
                       "chunk_samples": frames * side * side}
            first = folder / f"out-{args.compare_with}-{chunk_frames}" if args.compare_with else None
            for spec in args.tree:
                name, tree = spec.split("=", 1)
                out = folder / f"out-{name}-{chunk_frames}"
                out.mkdir(exist_ok=True)
                results[name] = {}
                for step in steps:
                    run = run_step(tree, folder, step, chunk_frames, out)
                    run["own_mb"] = run["peak_mb"] - run["base_mb"]
                    run["bytes_per_pixel"] = run["own_mb"] * 2**20 / side**2
                    results[name][step] = run
                    print(f"{name} {side}x{side} chunk {chunk_frames} ({frames} frames) {step}: "
                          f"{run['seconds']:.1f} s, peak {run['peak_mb']:.0f} MiB, own {run['own_mb']:.0f} MiB "
                          f"({run['bytes_per_pixel']:.0f} bytes a pixel)", flush=True)
                if first is None:
                    first = out
                else:
                    same = {p.name: identical(first / p.name, p) for p in sorted(out.glob("*.nc"))}
                    results[name]["identical_to_first"] = same
                    print(f"{name} against {first.name}: {same}", flush=True)
            with open(args.workdir / "calibration_memory.json", "a") as f:  # one line a run
                f.write(json.dumps(results) + "\n")
        if args.drop:
            import shutil

            shutil.rmtree(folder)
    print(f"load {os.getloadavg()}; {machine()}")


if __name__ == "__main__":
    sys.path[:0] = [str(REPO), str(REPO / "benchmarks")]
    main()
