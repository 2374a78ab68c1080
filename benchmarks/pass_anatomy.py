"""Why the fringe fit's workers are processes: one pass's streaming work in threads and in processes.

Runs the streaming part of one fit pass (:func:`dice_core.fringe_fit._accumulate`:
read, convert, two products per chunk) over the two parts of a simulated
baseline (:meth:`dice_core.io.FrameStream.split`): one after the other, in two
threads, and in two forked processes. Reuses the cube cached by
``fringe_fit.py`` (run that first with the same --frames and --workdir).

Usage::

    OPENBLAS_NUM_THREADS=1 python benchmarks/parallel_passes.py --frames 200000 --workdir /tmp/dice-fringe-bench
"""

from __future__ import annotations

import argparse
import concurrent.futures
import multiprocessing
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from fringe_fit import load  # noqa: E402

from dice_core.fringe_fit import _accumulate  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=200000)
    parser.add_argument("--workdir", type=Path, default=Path("benchmarks/out/fringe"))
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    _, _, stream = load(args.frames, args.workdir / f"n{args.frames}")
    lanes = stream.split(2)
    n_pixels = int(np.prod(stream.detector.shape))
    rng = np.random.default_rng(1)
    work = (rng.normal(size=(n_pixels, 3)), np.zeros(3), np.zeros(n_pixels), False)
    ways = {
        "one after the other": lambda: [_accumulate(lane, *work) for lane in lanes],
        "2 threads": lambda: list(concurrent.futures.ThreadPoolExecutor(2).map(lambda s: _accumulate(s, *work),
                                                                               lanes)),
        "2 forked processes": lambda: list(concurrent.futures.ProcessPoolExecutor(
            2, mp_context=multiprocessing.get_context("fork")).map(_accumulate, lanes, *[[w] * 2 for w in work])),
    }
    print(f"{args.frames} frames of {stream.detector.shape[0]}x{stream.detector.shape[1]}, "
          f"{stream.chunk_frames}-frame chunks, best of {args.repeat}:")
    chunk = rng.normal(size=(stream.chunk_frames, n_pixels)).astype(np.float32)
    projector = rng.normal(size=(n_pixels, 7)).astype(np.float32)
    narrow = [np.ascontiguousarray(projector[:, :3]), np.ascontiguousarray(projector[:, 3:])]
    products = {"one product with 7 columns": lambda: chunk @ projector,
                "products with 3 + 4 columns": lambda: np.hstack([chunk @ p for p in narrow])}
    n_chunks = args.frames // stream.chunk_frames
    for name, run in products.items():
        times = []
        for _ in range(args.repeat):
            start = time.perf_counter()
            for _ in range(n_chunks):
                run()
            times.append(time.perf_counter() - start)
        print(f"| {name}, {n_chunks} chunks | {min(times):.2f} s |")
    ways["one after the other"]()  # page cache
    for name, run in ways.items():
        times = []
        for _ in range(args.repeat):
            start = time.perf_counter()
            run()
            times.append(time.perf_counter() - start)
        print(f"| {name} | {min(times):.2f} s |")


if __name__ == "__main__":
    main()
