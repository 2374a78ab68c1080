"""Speed and memory of the global fringe solution of one baseline (issue 3's targets), through the library.

The workflow's own path (``snakemake --cores 2``) is measured by ``workflow_metrology.py``.

Simulates one 80x84 metrology baseline of N frames (default 200,000; cached in
--workdir), then measures, in one run on the same cube:

- ``plain pass``: one plain numpy pass over the cube (read in the same chunks,
  converted to float32 as the fit reads them, summed over frames), the reference
  for one iteration;
- ``fit``: the whole reduction of the baseline (:func:`dice_core.fringe_fit.fit_baseline`),
  in a fresh process that also reports its peak resident memory;
- ``LM per frame``: the paper's per-frame Levenberg-Marquardt spatial fit
  (scipy.optimize.least_squares, method "lm", 5 parameters B, A, phi, Kx, Ky)
  on a few hundred frames, extrapolated to N frames.

Usage::

    python benchmarks/fringe_fit.py --frames 200000 --workdir /tmp/dice-fringe-bench
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

BASELINE = "H1H4"


def config(frames):
    from dice_core import simulation

    return simulation.SimulationConfig.from_dict({
        "name": "fringe-bench", "frames_per_file": 20000,
        "dark": {"frames": 2}, "flats": {"frames": 2}, "stars": {"positions": 1, "frames": 1},
        "metrology": {"frames": frames, "sweep_frames": 1000,
                      "baselines": {BASELINE: {"period": 2.4, "angle_deg": 2.0}}, "pairs": {}},
    })


def prepare(frames, workdir):
    from dice_core import simulation
    from dice_core.io import write_product

    if (workdir / "dataset.yaml").exists():
        return
    cfg = config(frames)
    truth = simulation.make_truth(cfg)
    write_product(truth, workdir / "truth.nc", title="benchmark truth")
    start = time.perf_counter()
    for relpath, (kind, _, _, _) in simulation.file_jobs(cfg).items():
        if kind == "baseline":
            simulation.write_file(cfg, truth, relpath=relpath, outdir=workdir)
    simulation.write_manifest(cfg, workdir)
    print(f"simulated {frames} frames in {time.perf_counter() - start:.0f} s", file=sys.stderr)


def load(frames, workdir, chunk_frames="auto"):
    from dice_core import simulation
    from dice_core.io import FrameStream, read_product
    from dice_core.manifest import parse_manifest

    cfg = config(frames)
    manifest = parse_manifest(simulation.dataset_layout(cfg), workdir / "dataset.yaml")
    truth = read_product(workdir / "truth.nc")
    return manifest, truth, FrameStream(manifest.baselines[BASELINE], manifest.detector, dtype="float32",
                                        chunk_frames=chunk_frames)


def fit_child(frames, workdir, chunk_frames, workers):
    """The whole reduction, in this process; prints time, passes, accuracy and peak memory as JSON."""
    from dice_core import fringe_fit

    manifest, truth, stream = load(frames, workdir, chunk_frames)
    start = time.perf_counter()
    solution = fringe_fit.fit_baseline(stream, truth["bias"].values, detector=manifest.detector,
                                       flat=truth["sensitivity"].values, read_noise=truth["read_noise"].values,
                                       workers=workers)
    elapsed = time.perf_counter() - start
    n = solution.k / np.hypot(*solution.k)
    r, c = solution.rows, solution.cols
    p = n[0] * truth["dx"].values[r, c] + n[1] * truth["dy"].values[r, c]
    design = np.column_stack([np.ones_like(p), c, r])
    p -= design @ np.linalg.lstsq(design, p, rcond=None)[0]
    error = float(np.sqrt(np.nanmean((solution.offsets - p) ** 2)))
    floor = float(np.sqrt(np.nanmean(solution.photon_floor**2)))
    print(json.dumps({"seconds": elapsed, "passes": len(solution.history) + 1, "error": error, "floor": floor,
                      "peak_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                      "worker_peak_mib": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024}))


def plain_pass(stream):
    """One plain numpy pass: the same chunks, read, converted, summed over frames."""
    start = time.perf_counter()
    total = 0.0
    for chunk in stream:
        total = total + chunk.frames.sum(axis=0)
    return time.perf_counter() - start


def lm_per_frame(stream, detector, dark, n_frames):
    """Seconds per frame of a 5-parameter Levenberg-Marquardt fit of perfect-pixel fringes."""
    from scipy.optimize import least_squares

    from dice_core.fringes import initial_wavevector

    mask = np.ones(detector.shape, bool)  # the whole 80x84 frame, as the 8 ms figure
    rows, cols = np.nonzero(mask)
    frames = []
    for chunk in stream:
        frames.append(chunk.frames)  # each chunk is a fresh array
        if sum(len(f) for f in frames) >= n_frames:
            break
    frames = np.concatenate(frames)[:n_frames].astype(np.float64) - dark
    k0 = initial_wavevector(frames[0], mask)
    params = np.array([frames[0].mean(), frames[0].std() * np.sqrt(2), 0.0, *k0])

    def residual(p, data):
        return p[0] + p[1] * np.sin(p[3] * cols + p[4] * rows + p[2]) - data

    start = time.perf_counter()
    for frame in frames:
        # warm start from the previous frame, as the paper did
        params = least_squares(residual, params, args=(frame[mask],), method="lm").x
    return (time.perf_counter() - start) / len(frames)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=200000)
    parser.add_argument("--workdir", type=Path, default=Path("benchmarks/out/fringe"))
    parser.add_argument("--lm-frames", type=int, default=200)
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--chunk-frames", default="auto", help=argparse.SUPPRESS)
    parser.add_argument("--workers", type=int, default=1, help=argparse.SUPPRESS)
    args = parser.parse_args()
    workdir = args.workdir / f"n{args.frames}"
    if args.child:
        chunk_frames = args.chunk_frames if args.chunk_frames == "auto" else int(args.chunk_frames)
        return fit_child(args.frames, workdir, chunk_frames, args.workers)
    workdir.mkdir(parents=True, exist_ok=True)
    prepare(args.frames, workdir)
    manifest, truth, stream = load(args.frames, workdir)
    dark = truth["bias"].values
    plain_pass(stream)  # warm the page cache: every timing below reads from memory
    lm = lm_per_frame(stream, manifest.detector, dark, args.lm_frames)
    print("| frames | fit setting | plain numpy pass (s) | whole fit (s) | passes | per pass / plain pass | "
          "LM per frame (ms) | LM extrapolated (s) | LM / whole fit | peak RSS (MiB) | error / floor |")
    print("|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    # fit_baseline sets one BLAS thread itself (dice_core.parallel), whatever the environment says
    auto = f"auto chunks ({stream.chunk_frames} frames)"
    settings = [(f"2 worker processes, 1 BLAS thread, {auto} (library)", {}, "auto", 2),
                (f"1 process, 1 BLAS thread, {auto} (library)", {}, "auto", 1),
                ("1 process, 1 BLAS thread, 256-frame chunks (library)", {}, "256", 1)]
    for name, env, chunk_frames, workers in settings:
        # the plain pass reads the same chunks, next to each fit: the machine is noisy
        plain = plain_pass(load(args.frames, workdir, chunk_frames if chunk_frames == "auto" else int(chunk_frames))[2])
        out = subprocess.run([sys.executable, __file__, "--child", "--frames", str(args.frames), "--workdir",
                              str(args.workdir), "--chunk-frames", chunk_frames, "--workers", str(workers)],
                             check=True, capture_output=True, text=True, env={**os.environ, **env}).stdout
        fit = json.loads(out.strip().splitlines()[-1])
        iteration = fit["seconds"] / fit["passes"]
        peak = f"{fit['peak_mib']:.0f}" + (f" + {workers} x {fit['worker_peak_mib']:.0f}" if workers > 1 else "")
        print(f"| {args.frames} | {name} | {plain:.2f} | {fit['seconds']:.2f} | {fit['passes']} | "
              f"{iteration / plain:.2f} | {lm * 1e3:.2f} | {lm * args.frames:.0f} | "
              f"{lm * args.frames / fit['seconds']:.0f} | {peak} | {fit['error'] / fit['floor']:.3f} |",
              flush=True)


if __name__ == "__main__":
    main()
