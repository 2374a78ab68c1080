"""The staged tip refinement (``geometry.fit_two_source``) on large detectors, against known truth.

Each bench is ``tests/test_geometry.py``'s construction of a large detector (24 um pixels, fibers 600 mm
away, a baseline of period 2.4 or 4.0 pixels, its midpoint 11-16 mm off the normal; white offsets of
1e-3 pixel and phase noise of 3e-5 pixel; nominal tips ``--tip-off`` mm off the true ones, each along a
random direction) on a sample of its pixels:

- ``dense``: the 15 benches of 2048 to 4096 pixels a side (five sizes and baselines, seeds 0-2), every
  pixel's geometry on a 128x128 grid of them;
- ``sparse``: an 8192x8192 detector sampled on a regular 256x256 grid of pixels (a pixel every 32);
- ``random``: the same detector, 65,536 pixels at random positions;
- ``dead``: the sparse grid with 10 % of its pixels dead (dropped at random) and a dead quadrant-sized
  block off the centre;
- ``far``: the sparse grid with the nominal tips 2 and 3 mm off (``tip_sigma`` 1 mm: the prior itself
  2-3 sigma off);
- ``best``: the sparse grid with ``k_plane`` the best plane of the true phase over the pixels instead of its
  mean gradient (13e-3 rad/pixel apart along the baseline at period 2.4: a plane-wave solution may be
  either).

Every set but ``dense`` has two benches a seed, one a baseline (period 2.4 and 4.0).

Printed, per bench: converged or the error, the stages and iterations, the largest |error| / sigma of a
tip coordinate, and the rms and largest |error| / sigma along the tip modes the data pin (information ratio
above ``MODE_INFORMATION_THRESHOLD``): near 1 and within about 3 when the errors are calibrated. Then per
set: benches converged, rms of the pinned errors / sigma over them.

    python benchmarks/staged_tips.py sparse --seeds 0 1 2 3 4 5 6 7
    python benchmarks/staged_tips.py dense random dead far best
"""

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_geometry import PITCH, WAVELENGTH, large_bench

from dice_core import geometry
from dice_core.geometry import fit_two_source, two_source_phase

BASELINES = [(2.4, (0.012, 0.006), 0.035), (4.0, (-0.011, -0.010), 1.545)]
DENSE = [(2048, *BASELINES[0]), (2048, *BASELINES[1]), (3072, *BASELINES[0]), (4096, *BASELINES[1]),
         (4096, *BASELINES[0])]


def pixels_of(kind, side, rng):
    """Pixel coordinates (pixel) of a bench's sample."""
    if kind == "dense":
        step = side // 128
        rows, cols = np.mgrid[0:side:step, 0:side:step]
    elif kind == "random":
        flat = rng.choice(side * side, 256 * 256, replace=False)
        rows, cols = np.divmod(flat, side)
    else:
        rows, cols = np.mgrid[0:side:32, 0:side:32]
    x, y = cols.ravel().astype(float), rows.ravel().astype(float)
    if kind == "dead":
        alive = rng.random(x.size) > 0.1
        alive &= ~((x > side * 0.55) & (x < side * 0.8) & (y > side * 0.3) & (y < side * 0.55))
        x, y = x[alive], y[alive]
    return x, y


def bench(kind, side, period, midpoint, angle, seed, tip_off=(1e-3, 1e-3), best=False):
    """One bench (``tests/test_geometry.py``'s ``large_bench``): the pixel phases, their coordinates, the true
    and nominal tips (``tip_off``, m), k_plane (the true phase's mean gradient, or with ``best`` its best
    plane)."""
    rng = np.random.default_rng(seed)
    x, y = pixels_of(kind, side, rng)
    theta, truth, nominal, k_plane, _ = large_bench(x, y, side, period, midpoint, angle, rng, tip_off)
    if best:
        true = two_source_phase(x, y, *truth, wavelength=WAVELENGTH, pixel_pitch=PITCH)[0]
        k_plane = tuple(np.linalg.lstsq(np.array([np.ones(x.size), x, y]).T, true, rcond=None)[0][1:])
    return theta, x, y, truth, nominal, k_plane


class Stages(logging.Handler):
    def __init__(self):
        super().__init__(logging.INFO)
        self.stages, self.warnings = 0, 0

    def emit(self, record):
        self.stages += "tips refined over the" in record.getMessage()
        self.warnings += record.levelno >= logging.WARNING


def run(kind, side, period, midpoint, angle, seed):
    """Fits one bench of a set; prints a line; returns the pinned errors / sigma (None: not converged)."""
    tip_off = (2e-3, 3e-3) if kind == "far" else (1e-3, 1e-3)
    theta, x, y, truth, nominal, k_plane = bench("sparse" if kind in ("far", "best") else kind, side, period,
                                                 midpoint, angle, seed, tip_off, best=kind == "best")
    handler = Stages()
    logger = logging.getLogger("dice_core.geometry")
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    start = time.perf_counter()
    name = f"{kind:6} {side:5} {x.size:6} px  period {period}  seed {seed}"
    try:
        fit = fit_two_source(theta, x, y, *nominal, wavelength=WAVELENGTH, pixel_pitch=PITCH, k_plane=k_plane)
    except geometry.GeometryError as error:
        print(f"{name}  FAIL  {str(error)[:150]}", flush=True)
        return None
    finally:
        logger.removeHandler(handler)
    error = (fit.tips - truth).ravel()
    pinned = np.flatnonzero(fit.information > geometry.MODE_INFORMATION_THRESHOLD)
    modes = fit.tip_modes[:, pinned]
    z = (modes.T @ error) / np.sqrt(np.einsum("ik,ij,jk->k", modes, fit.tip_covariance, modes))
    print(f"{name}  ok    {handler.stages} stage(s) {fit.iterations:3} it  {time.perf_counter() - start:5.1f} s  "
          f"max |err|/sigma {np.max(np.abs(error / fit.tip_errors.ravel())):.2f}  pinned ({z.size}) rms "
          f"{np.sqrt(np.mean(z ** 2)):.2f} max {np.max(np.abs(z)):.2f}"
          f"{'  warned' if handler.warnings else ''}", flush=True)
    return z


def benches(kind, seeds):
    if kind == "dense":
        return [(kind, *case, seed) for case in DENSE for seed in seeds]
    return [(kind, 8192, *baseline, seed) for baseline in BASELINES for seed in seeds]


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("sets", nargs="+", choices=["dense", "sparse", "random", "dead", "far", "best"])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    args = parser.parse_args()
    for kind in args.sets:
        seeds = [0, 1, 2] if kind == "dense" and args.seeds == [0, 1, 2, 3] else args.seeds
        results = []
        for case in benches(kind, seeds):
            results.append(run(*case))
        done = [z for z in results if z is not None]
        z = np.concatenate(done) if done else np.zeros(0)
        print(f"{kind}: {len(done)}/{len(results)} converged; pinned errors / sigma rms "
              f"{np.sqrt(np.mean(z ** 2)) if z.size else np.nan:.2f}, largest {np.max(np.abs(z), initial=0):.2f} "
              f"over {z.size}\n", flush=True)


if __name__ == "__main__":
    main()
