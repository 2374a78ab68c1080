"""Peak memory of simulating and of streaming a cube, against the number of frames.

For each frame count, two fresh Python processes run one step each and report
their own peak resident memory (ru_maxrss), so one step's memory never hides
another's:

- ``simulate``: the simulator writes one 80x84 metrology baseline of N frames
  (in files of 20,000 frames, as on the bench);
- ``reduce``: the reader streams that acquisition through the PRNU
  statistics (per-frame normalisation, temporal mean and variance), the
  heaviest per-frame pass of this stage.

Usage::

    python benchmarks/memory_streaming.py --frames 2000 20000 100000 --workdir /tmp/dice-bench

Prints a Markdown table for BENCHMARKS.md. Needs about 2.7 GB of disk per
100,000 frames.
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

BASELINE = "H1H4"


def config(frames):
    from dice_core import simulation

    return simulation.SimulationConfig.from_dict({
        "name": "bench", "frames_per_file": 20000,
        "metrology": {"frames": frames, "baselines": {BASELINE: {"period": 2.4, "angle_deg": 2.0}},
                      "pairs": {}},
    })


def child(step, frames, workdir):
    """Run one step in this process and print its peak RSS (MiB) and duration (s) as JSON."""
    import numpy as np

    from dice_core import calibration, simulation
    from dice_core.io import FrameStream, read_product
    from dice_core.manifest import parse_manifest

    cfg = config(frames)
    raw = Path(workdir)
    start = time.perf_counter()
    if step == "simulate":
        truth = simulation.make_truth(cfg)
        from dice_core.io import write_product

        write_product(truth, raw / "truth.nc", title="benchmark truth")
        for relpath, (kind, name, _, _) in simulation.file_jobs(cfg).items():
            if kind == "baseline":
                simulation.write_file(cfg, truth, relpath=relpath, outdir=raw)
    else:
        read_product(raw / "truth.nc")
        manifest = parse_manifest(simulation.dataset_layout(cfg), raw / "dataset.yaml")
        stream = FrameStream(manifest.baselines[BASELINE], manifest.detector)
        zero = np.zeros(manifest.detector.shape)
        calibration.prnu_map(stream, zero, dark_noise=zero + 4.0, detector=manifest.detector,
                             n_frames=stream.n_frames)
    elapsed = time.perf_counter() - start
    peak_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux reports KiB
    print(json.dumps({"step": step, "frames": frames, "peak_mib": peak_mib, "seconds": elapsed}))


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, nargs="+", default=[2000, 20000, 100000])
    parser.add_argument("--workdir", type=Path, default=Path("benchmarks/out/memory"))
    parser.add_argument("--child", nargs=2, metavar=("STEP", "FRAMES"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        return child(args.child[0], int(args.child[1]), args.workdir)

    rows = []
    for frames in args.frames:
        workdir = args.workdir / f"n{frames}"
        shutil.rmtree(workdir, ignore_errors=True)
        workdir.mkdir(parents=True)
        for step in ("simulate", "reduce"):
            out = subprocess.run([sys.executable, __file__, "--child", step, str(frames), "--workdir", str(workdir)],
                                 check=True, capture_output=True, text=True).stdout
            rows.append(json.loads(out.strip().splitlines()[-1]))
            print(f"{step:8s} {frames:7d} frames: peak {rows[-1]['peak_mib']:.0f} MiB, "
                  f"{rows[-1]['seconds']:.1f} s", file=sys.stderr)
        shutil.rmtree(workdir, ignore_errors=True)
    print("| step | frames | data (MiB) | peak RSS (MiB) | time (s) |")
    print("|---|---:|---:|---:|---:|")
    for r in rows:
        data = r["frames"] * 80 * 84 * 2 / 2**20
        print(f"| {r['step']} | {r['frames']} | {data:.0f} | {r['peak_mib']:.0f} | {r['seconds']:.1f} |")


if __name__ == "__main__":
    main()
