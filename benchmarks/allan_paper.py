"""Allan deviations at the paper's scale: 200,000 frames, B = 10000 adu, A = 6000 adu, 10 e-/adu.

Reuses (or simulates) the 80x84 baseline of ``fringe_fit.py`` (the paper
preset's metrology: sweep of 1000 frames, laser intensity noise 1e-2, phase
jitter 1e-2 rad, read noise 4 adu), runs the global fit, then the Allan step
(one more pass over the frames), and prints the curve with its photon-noise
limits, the value at 100,000 frames per group (the paper's last point: 2e-5
pixel for pixels, 2e-6 for 10x10 blocks), the Allan step's time and the peak
memory.

Usage::

    python benchmarks/allan_paper.py --frames 200000 --workdir /tmp/dice-fringe-bench
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

import xarray as xr

sys.path.insert(0, str(Path(__file__).parent))
from fringe_fit import load, prepare  # noqa: E402

from dice_core import allan, fringe_fit, fringes  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=200000)
    parser.add_argument("--workdir", type=Path, default=Path("benchmarks/out/fringe"))
    args = parser.parse_args()
    workdir = args.workdir / f"n{args.frames}"
    workdir.mkdir(parents=True, exist_ok=True)
    prepare(args.frames, workdir)
    manifest, truth, stream = load(args.frames, workdir)
    start = time.perf_counter()
    solution = fringe_fit.fit_baseline(stream, truth["bias"].values, detector=manifest.detector,
                                       flat=truth["sensitivity"].values, read_noise=truth["read_noise"].values,
                                       workers=2)
    fit_seconds = time.perf_counter() - start
    metrology = fringes.solution_dataset(solution, manifest.detector)
    dark = xr.Dataset({"dark": (("row", "col"), truth["bias"].values),
                       "noise": (("row", "col"), truth["read_noise"].values)})
    start = time.perf_counter()
    ds = allan.allan_of_baseline(stream, metrology, dark=dark, detector=manifest.detector, workers=2)
    allan_seconds = time.perf_counter() - start
    print(f"{args.frames} frames; fit {fit_seconds:.1f} s; Allan step {allan_seconds:.1f} s; "
          f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB; "
          f"{ds.sizes['batch']} batches of {ds.attrs['frames_per_batch']:.0f} frames; slope {float(ds['slope']):.3f}")
    print("| frames per group | pixels (pixel) | photon limit | paper's limit | 10x10 blocks (pixel) | photon limit "
          "| paper's limit |")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    for i in range(ds.sizes["n_frames"]):
        row = ds.isel(n_frames=i)
        print(f"| {float(row['n_frames']):.0f} | {float(row['deviation_mean']):.2e} | "
              f"{float(row['photon_limit_pixel']):.2e} | {float(row['photon_limit_pixel_paper']):.2e} | "
              f"{float(row['deviation_block_mean']):.2e} | {float(row['photon_limit_block']):.2e} | "
              f"{float(row['photon_limit_block_paper']):.2e} |")
    at = ds.interp(n_frames=min(100000.0, float(ds["n_frames"][-1])), method="linear")
    print(f"at {float(at['n_frames']):.0f} frames per group (interpolated): pixels "
          f"{float(at['deviation_mean']):.2e}, blocks {float(at['deviation_block_mean']):.2e} pixel")


if __name__ == "__main__":
    main()
