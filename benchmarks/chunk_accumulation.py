"""A fringe-fit pass's accumulation against the frames per chunk, on synthetic frames (library level).

    OPENBLAS_NUM_THREADS=1 python benchmarks/chunk_accumulation.py 1024 128 1 4 16 32 64 128

Arguments: the detector's side (pixels), the frames, then the chunk sizes (frames) to time. Each chunk
size runs ``dice_core.fringe_fit._accumulate`` (pass 1's 7-column projector, the reference subtracted
from each chunk) over the same float32 frames twice; the faster is printed, in s per 1e9 samples.
BENCHMARKS.md, "A large detector", quotes it (why auto chunks hold at least 16 frames).
"""

import sys
import time

import numpy as np

from dice_core.fringe_fit import _accumulate
from dice_core.io import Chunk


def main(argv):
    side, frames, sizes = int(argv[0]), int(argv[1]), [int(a) for a in argv[2:]]
    pixels = side * side
    rng = np.random.default_rng(0)
    cube = rng.integers(0, 60000, size=(frames, side, side)).astype(np.float32)
    projector, offset, centre = rng.standard_normal((pixels, 7)), rng.standard_normal(7), rng.standard_normal(pixels)
    for n in sizes:
        chunks = [Chunk(s, cube[s:s + n], None, False) for s in range(0, frames, n)]
        best = np.inf
        for _ in range(2):
            start = time.perf_counter()
            _accumulate(chunks, projector, offset, centre, True)
            best = min(best, time.perf_counter() - start)
        print(f"{side}x{side}, chunks of {n:3d} frames: {best / (pixels * frames) * 1e9:.2f} s per 1e9 samples",
              flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
