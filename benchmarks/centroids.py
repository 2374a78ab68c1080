"""The centroid step at the paper preset's scale, through the library: 90 positions of 100 frames on the paper's
80x84 detector (its stars: 0.17-pixel steps, 5e-3 rad tip-tilt), 4 batches, every calibration mode, both methods.

    python benchmarks/centroids.py --workdir /tmp/dice-centroids [--against REV] [--profile MODE:METHOD]

The dataset is simulated once into the work folder (its stars only; the calibrations are the truth's, as the
tests take them). Prints each (mode, method)'s time for :func:`dice_core.centroids.measure_positions`, and, in
the same run, one plain pass that reads every position's stack product (the step's own input reading), for a
ratio. ``--against REV`` also runs ``dice_core/centroids.py`` as it was at the git revision REV on the same
stacks, alternating with today's (each mode and method old then new), and prints the ratio of their times and
the largest difference of every product over the old Cramer-Rao bound.
"""

import argparse
import cProfile
import importlib.util
import pstats
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from dice_core import centroids, simulation, stacks
from dice_core.io import FrameStream, read_product, write_product
from dice_core.manifest import load_manifest

PAPER_STARS = {"positions": 90, "frames": 100, "step": [0.0, 0.17], "tip_tilt_pv": 5.0e-3}


def dataset(workdir: Path):
    """The simulated stars (and their truth), simulated on the first call."""
    raw = workdir / "raw"
    if not (raw / "dataset.yaml").exists():
        cfg = simulation.SimulationConfig.from_dict({
            "name": "centroids-bench", "seed": 20150926, "frames_per_file": 20000,
            "detector": {"shape": [80, 84], "science_rows": [2, 79], "science_cols": [10, 83], "gain": 10.0,
                         "read_noise": 4.0},
            "dark": {"frames": 2}, "flats": {"frames": 2},
            "metrology": {"frames": 2, "baselines": {"H1H4": {"period": 2.4, "angle_deg": 2.0}}, "pairs": {}},
            "stars": PAPER_STARS})
        simulation.simulate_dataset(cfg, raw)
    return load_manifest(raw / "dataset.yaml"), read_product(raw / "truth.nc")


def stack_paths(manifest, workdir: Path, n_batches: int):
    """Each position's stack product, as the workflow's stack_position step writes it (made on the first call)."""
    paths = []
    for p in manifest.positions:
        path = workdir / "stars" / f"{p.index}.nc"
        if not path.exists():
            stream = FrameStream(p.acquisition, manifest.detector)
            stack = stacks.stack_position(stream, stream.n_frames, n_batches=n_batches, position=p.index)
            write_product(stack.to_dataset(), path, title="bench stack", config={}, inputs=list(p.acquisition.files))
        paths.append(path)
    return paths


def read_stacks(paths):
    return [stacks.PositionStack.from_dataset(read_product(path)) for path in paths]


def module_at(rev: str):
    """dice_core/centroids.py as it was at the git revision ``rev``, imported as a module of its own."""
    source = subprocess.run(["git", "show", f"{rev}:dice_core/centroids.py"], check=True, capture_output=True,
                            text=True, cwd=Path(__file__).resolve().parents[1]).stdout
    path = Path(tempfile.mkdtemp()) / "centroids_at_rev.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location("centroids_at_rev", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def measure(manifest, truth, position_stacks, mode, method, module=centroids):
    use_flat, use_metrology = centroids.mode_corrections(mode)
    widths = "widths" in centroids.mode_needs(mode)
    zero = np.zeros(manifest.detector.shape)
    return module.measure_positions(
        position_stacks, [p.index for p in manifest.positions], approx=manifest.star_approx,
        detector=manifest.detector, dark=truth["bias"].values, read_noise=np.full(manifest.detector.shape, 4.0),
        prnu=truth["sensitivity"].values if use_flat else None,
        dx=truth["dx"].values if use_metrology else None, dy=truth["dy"].values if use_metrology else None,
        variance_x=zero if widths else None, variance_y=zero if widths else None, method=method)


FIELDS = ("x", "y", "precision_x", "precision_y", "limit_x", "limit_y")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/dice-centroids"))
    parser.add_argument("--batches", type=int, default=4)
    parser.add_argument("--modes", nargs="*", default=["raw", "flat", "metrology", "flat+metrology",
                                                       "flat+metrology+width"])
    parser.add_argument("--methods", nargs="*", default=list(centroids.METHODS))
    parser.add_argument("--profile", help="MODE:METHOD to profile (cProfile, top 25 by total time)")
    parser.add_argument("--against", metavar="REV", help="also time (and compare with) the code at this revision")
    args = parser.parse_args()
    manifest, truth = dataset(args.workdir)
    paths = stack_paths(manifest, args.workdir, args.batches)
    start = time.perf_counter()
    position_stacks = read_stacks(paths)
    read_time = time.perf_counter() - start
    print(f"{len(paths)} positions, {len(manifest.star_approx)} stars; reading the stacks: {read_time:.2f} s")
    if args.profile:
        mode, method = args.profile.split(":")
        profile = cProfile.Profile()
        profile.runcall(measure, manifest, truth, position_stacks, mode, method)
        pstats.Stats(profile).sort_stats("tottime").print_stats(25)
        return
    old_module = module_at(args.against) if args.against else None
    totals = {"new": 0.0, "old": 0.0}
    for method in args.methods:
        for mode in args.modes:
            results = {}
            for name, module in (("old", old_module), ("new", centroids)):
                if module is None:
                    continue
                start = time.perf_counter()
                results[name] = measure(manifest, truth, position_stacks, mode, method, module)
                elapsed = time.perf_counter() - start
                totals[name] += elapsed
                print(f"{mode:22s} {method:9s} {name} {elapsed:7.2f} s", flush=True)
            if old_module is not None:
                print(f"{'':32s} max |new - old| / Cramer-Rao bound: {differences(*results.values())}")
    print(f"total {totals['new']:.2f} s, {totals['new'] / read_time:.1f}x the stacks' read")
    if old_module is not None:
        print(f"at {args.against}: {totals['old']:.2f} s, {totals['old'] / read_time:.1f}x the stacks' read; "
              f"{totals['old'] / totals['new']:.1f}x today's")


def differences(old, new):
    """The largest |new - old| of every product over the old result's Cramer-Rao bound (NaNs must agree)."""
    worst = {}
    for field in FIELDS:
        a, b = getattr(old, field), getattr(new, field)
        assert np.array_equal(np.isnan(a), np.isnan(b)), f"{field}: NaNs differ"
        bound = getattr(old, f"limit_{field[-1]}")
        worst[field] = float(np.nanmax(np.abs(a - b) / bound)) if np.isfinite(a).any() else 0.0
    return ", ".join(f"{k} {v:.1e}" for k, v in worst.items())


if __name__ == "__main__":
    main()
