"""Where a batch's extra Allan deviation came from (issue 27): the numbers of docs/metrology.md.

Four baselines of the default preset's bench (80x84 pixels, periods 2.4 and 4 pixel, spherical waves, the
preset's noise) at 20,000 frames each, or the sweep and fringe that ``--sweep steep`` names (6 periods each way
in 900 frames, time constant 0.15, a 3.1-pixel fringe at 30 degrees: the test's held-out case), are simulated
and fitted once; then the Allan groups are formed four ways: the batches as the shortest runs sweeping a fringe
period (unequal lengths, before issue 27) or of one length (any run that long sweeps a period), each fitting
appendix B's three linear terms or the pixel's phase alone (iota and alpha the global solution's). For each
way it prints the single batch's and the largest group's deviation over the global solution's floor scaled to
their frames, sqrt(N_total / N), over the uniform-sampling floor sqrt(B iota / g + sr^2) / (A alpha |K|
sqrt(N/2)), and the log-log slope over every group size; and, from the sweep alone, the Jensen factor
sqrt(mean(1/N_b) mean(N_b)) of the unequal lengths. Run by hand (about 3 min on 2 shared cores):

    python benchmarks/allan_batches.py [--frames 20000] [--sweep steep]
"""

import argparse
import tempfile
from pathlib import Path

import numpy as np

from dice_core import allan, fringe_fit, fringes, simulation
from dice_core.geometry import BaselineGeometry
from dice_core.io import FrameStream, first_chunk, read_product
from dice_core.manifest import load_manifest

STEEP = {"metrology.sweep_cycles": 6.0, "metrology.sweep_frames": 900, "metrology.sweep_time_constant": 0.15,
         "metrology.spherical": False,
         "metrology.baselines": {"B31": {"period": 3.1, "angle_deg": 30.0}}, "metrology.pairs": {}}


def ways(stream, metrology, truth, detector):
    """The four ways' statistics: {(equal_length, phase_only): AllanStatistics}."""
    phase = metrology["phase"].values
    rows, cols = np.nonzero(np.isfinite(metrology["projected_offset"].values))
    k = np.array([float(metrology["kx"]), float(metrology["ky"])])
    reference_phase = metrology["pixel_phase"].values[rows, cols]
    iota, alpha = metrology["iota"].values[rows, cols], metrology["alpha"].values[rows, cols]
    pixel_factors = np.column_stack([iota, alpha * np.sin(reference_phase), alpha * np.cos(reference_phase)])
    level, amplitude = metrology["level"].values, metrology["amplitude"].values
    factors = np.column_stack([level, amplitude * np.cos(phase), amplitude * np.sin(phase)])
    dark, read_noise = truth["bias"].values, truth["read_noise"].values[rows, cols]
    reference = first_chunk(stream).frames.mean(axis=0)
    out = {}
    for equal_length in (False, True):
        batches = allan.fringe_batches(phase, equal_length=equal_length)
        for phase_only in (False, True):
            offsets, sums = allan.batch_offsets(stream.centred(reference), batches, factors, dark, reference_phase,
                                                k, rows, cols, pixel_factors=pixel_factors if phase_only else None,
                                                reference=reference, return_sums=True)
            good = np.isfinite(offsets).all(axis=0)
            floors = allan.batch_floors(factors, batches, pixel_factors=pixel_factors, gain=detector.gain,
                                        read_noise=read_noise, k_norm=np.hypot(*k), phase_only=phase_only)
            groups = allan.group_fits(sums, batches, factors, reference_phase, k, rows, cols,
                                      allan.group_sizes(len(batches)), pixel_factors=pixel_factors,
                                      gain=detector.gain, read_noise=read_noise, good=good,
                                      weights=allan.block_weights(rows, cols, good=good), phase_only=phase_only)
            out[equal_length, phase_only] = allan.allan_statistics(
                offsets, floors, batches, rows, cols, gain=detector.gain, level=float(level.mean()),
                amplitude=float(amplitude.mean()), iota=iota, alpha=alpha, read_noise=read_noise, k=k,
                groups=groups, global_floor=(metrology["photon_noise_floor"].values[rows, cols], phase.size))
    jensen = np.diff(allan.fringe_batches(phase, equal_length=False), axis=1)[:, 0]
    return out, float(np.sqrt(np.mean(1 / jensen) * np.mean(jensen))), (int(jensen.min()), int(jensen.max()))


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=20000)
    parser.add_argument("--sweep", choices=["default", "steep"], default="default")
    args = parser.parse_args()
    overrides = {"metrology.frames": args.frames, "frames_per_file": 100000, "stars.positions": 1,
                 "dark.frames": 2, "flats.frames": 2, **(STEEP if args.sweep == "steep" else {})}
    cfg = simulation.load_preset(Path(__file__).parents[1] / "config/presets/default.yaml", overrides)
    print("| baseline | batches | frames per batch | fit | single batch / global floor scaled | / uniform floor "
          "| largest group / global | slope |")
    print("|---|---|---:|---|---:|---:|---:|---:|")
    with tempfile.TemporaryDirectory() as folder:
        manifest = load_manifest(simulation.simulate_dataset(cfg, Path(folder)))
        truth = read_product(Path(folder) / "truth.nc").load()
        for baseline in manifest.baselines:
            stream = FrameStream(manifest.baselines[baseline], manifest.detector, dtype="float32")
            geometry = None if manifest.geometry is None else BaselineGeometry.of_baseline(manifest.geometry,
                                                                                            baseline)
            solution = fringe_fit.fit_baseline(stream, truth["bias"].values, detector=manifest.detector,
                                               flat=truth["sensitivity"].values,
                                               read_noise=truth["read_noise"].values, label=baseline,
                                               geometry=geometry, workers=2)
            metrology = fringes.solution_dataset(solution, manifest.detector,
                                                 fibers=None if geometry is None else geometry.fibers)
            results, jensen, span = ways(stream, metrology, truth, manifest.detector)
            for (equal_length, phase_only), s in results.items():
                batches = "one length" if equal_length else f"shortest runs ({span[0]}-{span[1]})"
                fit = "phase alone" if phase_only else "three terms"
                print(f"| {baseline} | {batches} | {s.frames_per_batch:.0f} | {fit} | "
                      f"{s.deviation_mean[0] / s.photon_limit_pixel_global[0]:.3f} | "
                      f"{s.deviation_mean[0] / s.photon_limit_pixel_paper[0]:.3f} | "
                      f"{s.deviation_mean[-1] / s.photon_limit_pixel_global[-1]:.3f} | {s.slope:.3f} |")
            print(f"| {baseline} | Jensen factor of the shortest runs: {jensen:.3f} | | | | | | |")


if __name__ == "__main__":
    main()
