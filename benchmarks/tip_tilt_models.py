"""Tip-tilt's excess variance under each superimposition: the numbers of docs/astrometry.md ("Tip-tilt").

Twin simulations: the star-accuracy bench (dice_core.studies.STAR_ACCURACY_BENCH: the simulated stage, its
star pattern 2 degrees off axis at 25000 pixel, perfect flat and metrology) with the same seed and detector,
the stage's tip-tilt walks at 0, 5e-3 (the paper's) and 2e-2 rad peak to valley. For each, the flat+metrology
centroids, then each model's corrected accuracy over positions; excess^2 = accuracy(tilted)^2 -
accuracy(untilted)^2, and the share of Procrustes's excess variance each model removes. With
--photon-noise, the bench's photon and read noise are on (the paper's regime, where the excess is small
against the other errors); without, only what perfect calibrations leave (PRF width spread) remains. For each
tilted twin it also prints the share of Procrustes's excess the pose removes beside the share the true tip and
tilt remove and the noise-limited bound of the pose's Fisher information (issue 27;
dice_core.studies.tip_tilt_removals). --off-axis-deg sets the bench's field, --pose-off-axis-deg the pose's
nominal one where it is not the bench's, --frames the frames per position. With several seeds it ends with
the pose's removal and bound over them. Run by hand (about a minute per
configuration on 2 cores):

    python benchmarks/tip_tilt_models.py --positions 33 [--photon-noise] [--seeds 3]
    python benchmarks/tip_tilt_models.py --positions 60 --photon-noise --frames 240 --amplitudes 8e-3 \
        --off-axis-deg 0 --pose-off-axis-deg 2     # the issue's twins on an on-axis bench, the presets' nominal
    python benchmarks/tip_tilt_models.py --positions 60 --photon-noise --frames 240 --amplitudes 8e-3 \
        --off-axis-deg 0 --trials 500 --seeds 9   # the issue's twins over nine seeds
"""

import argparse
import dataclasses
import logging

import numpy as np

from dice_core import accuracies, studies, superimposition
from dice_core.studies import flat_metrology_centroids

MODELS = ("procrustes", "projective", "pose")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--positions", type=int, default=33)
    parser.add_argument("--photon-noise", action="store_true")
    parser.add_argument("--seeds", type=int, default=1, help="twin pairs with seeds 20150926, +1, ...")
    parser.add_argument("--amplitudes", type=float, nargs="+", default=[5e-3, 2e-2])
    parser.add_argument("--trials", type=int, default=1000)
    parser.add_argument("--frames", type=int, default=16, help="frames per position")
    parser.add_argument("--off-axis-deg", type=float, default=2.0, help="the bench's field, degrees off axis")
    parser.add_argument("--pose-off-axis-deg", type=float, default=None, help="the pose's nominal (the bench's)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    noise = {"detector.photon_noise": True, "detector.read_noise": 4.0} if args.photon_noise else {}
    excess = {(a, m): [] for a in args.amplitudes for m in MODELS}
    shares = {a: [] for a in args.amplitudes}  # (measured, bound) of the pose, per seed
    for seed in range(20150926, 20150926 + args.seeds):
        found, centroids = {}, {}  # not 'accuracies': the module's name
        for amplitude in [0.0, *args.amplitudes]:
            settings = studies.apply_overrides(studies.STAR_ACCURACY_BENCH, {
                "seed": seed, "stars.positions": args.positions, "stars.tip_tilt_pv": amplitude,
                "stars.frames": args.frames, "stars.off_axis_deg": args.off_axis_deg, **noise})
            configurations, truth, geometry = flat_metrology_centroids(settings)
            if args.pose_off_axis_deg is not None:
                geometry = dataclasses.replace(geometry, off_axis=np.radians(args.pose_off_axis_deg))
            centroids[amplitude] = (configurations, truth)
            for model in MODELS:
                result = accuracies.accuracy(configurations, model=model, geometry=geometry, trials=args.trials)
                found[amplitude, model] = result
                line = (f"seed {seed} tip-tilt {amplitude:.0e} rad PV  {model:10s} accuracy {result.accuracy:.3e} "
                        f"+- {result.error:.1e} pixel (rms residual {result.rms_residual:.3e}, factor {result.factor:.3f})")
                if model == "pose" and amplitude > 0:
                    report = superimposition.pose_identifiability(result.result, sigma=result.accuracy)
                    stage = truth["stage_rotation"].values
                    errors = (result.result.poses[:, 3:5] - stage[:, :2]) / report.crlb_nominal_field[:, 3:5]
                    line += (f"\n      identifiable {report.identifiable}, tip/tilt SNR {report.snr['tip']:.1f}/"
                             f"{report.snr['tilt']:.1f}, CRLB from the data {np.sqrt(np.mean(report.crlb[:, 3:5]**2)):.1e}"
                             f" rad, with the field known {np.sqrt(np.mean(report.crlb_nominal_field[:, 3:5]**2)):.1e}"
                             f" rad; fitted minus true in the latter's units: rms {np.sqrt(np.mean(errors**2)):.2f}")
                print(line, flush=True)
        for amplitude in args.amplitudes:
            for model in MODELS:
                excess[amplitude, model].append(found[amplitude, model].accuracy ** 2
                                                - found[0.0, model].accuracy ** 2)
            (tilted, truth), (untilted, _) = centroids[amplitude], centroids[0.0]
            removals = studies.tip_tilt_removals(
                [found[a, "procrustes"] for a in (amplitude, 0.0)], [found[a, "pose"] for a in (amplitude, 0.0)],
                tilted=tilted, untilted=untilted, true_tip_tilt=truth["stage_rotation"].values[:, :2],
                trials=args.trials)
            shares[amplitude].append((removals["pose_removal"][0], removals["pose_removal_bound"][0]))
            print(f"seed {seed} tip-tilt {amplitude:.0e} rad PV: " + ", ".join(
                f"{name} {value:.3f}" for name, (value, _) in removals.items()), flush=True)
    print(f"\nexcess variance of flat+metrology over positions ({args.positions} positions, photon noise "
          f"{'on' if args.photon_noise else 'off'}, {args.seeds} twin pair(s)), pixel^2:")
    for amplitude in args.amplitudes:
        procrustes = np.mean(excess[amplitude, "procrustes"])
        parts = []
        for model in MODELS:
            value = np.mean(excess[amplitude, model])
            parts.append(f"{model} {value:+.2e} (excess {np.sign(value) * np.sqrt(abs(value)):.2e} pixel, "
                         f"removes {100 * (1 - value / procrustes):.0f}% of Procrustes's)")
        print(f"  {amplitude:.0e} rad PV: " + "; ".join(parts))
        measured, bound = np.array(shares[amplitude]).T
        if len(measured) > 1:
            ratio = measured / bound
            print(f"    pose over {len(measured)} seeds: removes {measured.mean():.3f} +- "
                  f"{measured.std(ddof=1) / np.sqrt(len(measured)):.3f}, bound {bound.mean():.3f}, removes / bound "
                  f"{ratio.mean():.2f} +- {ratio.std(ddof=1) / np.sqrt(len(ratio)):.2f} (lowest {ratio.min():.2f})")


if __name__ == "__main__":
    main()
