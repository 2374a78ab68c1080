"""The simulation's chunk of frames against its speed: one metrology file written at several chunk sizes.

The simulator makes each chunk's signal and noise in float64 temporaries (``dice_core.simulation._read_out``):
a few passes over the chunk. A chunk that stays in a core's cache streams those passes faster than one that
does not. This writes one FITS file of a preset's first baseline (``simulation.write_file``, as the workflow's
``simulate_file`` job does, the truth read once beforehand) with ``SIMULATION_CHUNK_SAMPLES`` set to each size
given, the sizes alternating over ``--repeats`` rounds in one process, and prints each size's median time, the
file's SHA-256 (the same for every size: the frames do not depend on the chunk) and the ratio to the first
size given.

    python benchmarks/simulation_chunks.py [--preset paper] [--repeats 3] 2097152 262144 ...
"""

from __future__ import annotations

import argparse
import hashlib
import platform
import statistics
import tempfile
import time
from pathlib import Path

from dice_core import simulation

REPO = Path(__file__).resolve().parents[1]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sizes", nargs="+", type=int, help="chunk sizes in samples (pixels x frames)")
    parser.add_argument("--preset", default="paper", help="simulation preset (config/presets/<name>.yaml)")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    cfg = simulation.load_preset(REPO / "config" / "presets" / f"{args.preset}.yaml")
    relpath = next(rel for rel, (kind, *_) in simulation.file_jobs(cfg).items() if kind == "baseline")
    truth = simulation.make_truth(cfg)
    pixels = cfg.detector.shape[0] * cfg.detector.shape[1]
    times = {size: [] for size in args.sizes}
    digests = {}
    with tempfile.TemporaryDirectory() as out:
        for _ in range(args.repeats):
            for size in args.sizes:
                simulation.SIMULATION_CHUNK_SAMPLES = size
                start = time.perf_counter()
                path = simulation.write_file(cfg, truth, relpath=relpath, outdir=out)
                times[size].append(time.perf_counter() - start)
                digests.setdefault(size, set()).add(hashlib.sha256(path.read_bytes()).hexdigest())
    frames = simulation.file_jobs(cfg)[relpath][3] - simulation.file_jobs(cfg)[relpath][2]
    print(f"{platform.processor() or platform.machine()}, preset {args.preset}, {relpath}: {frames} frames of "
          f"{cfg.detector.shape[0]}x{cfg.detector.shape[1]}; {args.repeats} rounds")
    print("| chunk (samples) | frames a chunk | median (s) | s per 1e9 samples | / first size | SHA-256 |")
    print("|---:|---:|---:|---:|---:|---|")
    first = statistics.median(times[args.sizes[0]])
    for size in args.sizes:
        median = statistics.median(times[size])
        simulation.SIMULATION_CHUNK_SAMPLES = size
        chunk = simulation.simulation_chunk_frames(cfg)
        print(f"| {size} | {chunk} | {median:.2f} | {median / (frames * pixels) * 1e9:.1f} | "
              f"{median / first:.2f} | {', '.join(d[:12] for d in sorted(digests[size]))} |")
    if len({d for found in digests.values() for d in found}) != 1:
        raise SystemExit("the files differ between chunk sizes")


if __name__ == "__main__":
    main()
