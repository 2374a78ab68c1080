"""Accuracy of the spherical-wave reduction on the default geometry: the numbers of docs/metrology.md.

Simulates the default preset's bench (80x84 pixels, fibers 600 mm away, baseline midpoints 9-18 mm off the
normal, nominal tips exactly 1 mm off the true ones) with 2000 frames per baseline, reduces every baseline
with and without the geometry, and prints, against the truth:

- per baseline: the declared modes and the tip modes' information ratios, the offsets' error over the photon
  floor, the plane-wave fit's error over the floor, the pinned tip modes' errors in sigma;
- per pair: dx and dy errors over their floors; the pair difference against its floor;
- the principal angles between the two pairs' mode spaces;
- the variation of |K| across the detector; the departure from a plane over the whole detector.

Run by hand (about 30 s on 2 cores):

    python benchmarks/spherical_waves.py
"""

import tempfile
from pathlib import Path

import numpy as np

from dice_core import deprojection, fringe_fit, fringes, geometry, simulation
from dice_core.geometry import BaselineGeometry, remove_modes, two_source_phase
from dice_core.io import FrameStream, read_product
from dice_core.manifest import load_manifest

BASELINES = {
    "H1H4": {"period": 2.4, "angle_deg": 2.0, "midpoint": [0.012, 0.006]},
    "V1V4": {"period": 2.4, "angle_deg": 93.0, "midpoint": [-0.004, 0.008]},
    "H2H4": {"period": 4.0, "angle_deg": -3.0, "midpoint": [0.016, -0.009]},
    "V2V4": {"period": 4.0, "angle_deg": 88.5, "midpoint": [-0.011, -0.010]},
}


def rms(values):
    return float(np.sqrt(np.nanmean(np.square(values))))


def main():
    cfg = simulation.SimulationConfig.from_dict({
        "name": "spherical-benchmark", "frames_per_file": 100000,
        "detector": {"shape": [80, 84], "science_rows": [2, 79], "science_cols": [10, 83]},
        "dark": {"frames": 2}, "flats": {"frames": 2}, "stars": {"positions": 1, "frames": 1},
        "metrology": {"frames": 2000, "spherical": True, "tip_error": [1.0e-3, 1.0e-3], "baselines": BASELINES,
                      "pairs": {"P14": ["H1H4", "V1V4"], "P24": ["H2H4", "V2V4"]}},
    })
    with tempfile.TemporaryDirectory() as folder:
        manifest = load_manifest(simulation.simulate_dataset(cfg, Path(folder)))
        truth = read_product(Path(folder) / "truth.nc").load()
        solutions = {b: fringe_fit.fit_baseline(
            FrameStream(manifest.baselines[b], manifest.detector), truth["bias"].values, detector=manifest.detector,
            flat=truth["sensitivity"].values, read_noise=truth["read_noise"].values,
            geometry=BaselineGeometry.of_baseline(manifest.geometry, b), label=b) for b in manifest.baselines}
    bench = manifest.geometry
    tips = dict(zip(truth["fiber"].values, truth["fiber_position"].values))
    products = {}
    print("baseline  modes  information ratios               error/floor  plane-wave error/floor (pixel)"
          "  pinned tip errors [sigma]")
    for b, solution in solutions.items():
        fit = solution.two_source
        active = ~solution.masked
        r, c = solution.rows[active], solution.cols[active]
        true_tips = [tips[f] for f in bench.baseline_fibers[b]]
        _, gx, gy = two_source_phase(c, r, *true_tips, wavelength=bench.wavelength, pixel_pitch=bench.pixel_pitch)
        n = fit.sign * np.column_stack([gx, gy]) / np.hypot(gx, gy)[:, None]
        affine = geometry.affine_basis(c, r)
        truth_p = n[:, 0] * truth["dx"].values[r, c] + n[:, 1] * truth["dy"].values[r, c]
        floor = rms(solution.photon_floor)
        ratio = rms(solution.offsets[active] - remove_modes(remove_modes(truth_p, affine), fit.modes)) / floor
        k_plane, plane = fringes.projected_offsets(solution.pixel_phase[active], c.astype(float), r.astype(float),
                                                   solution.k)
        n_plane = k_plane / np.hypot(*k_plane)
        plane_error = rms(plane - remove_modes(n_plane[0] * truth["dx"].values[r, c]
                                               + n_plane[1] * truth["dy"].values[r, c], affine))
        error = fit.tips.ravel() - np.ravel(true_tips)
        pinned = [(fit.tip_modes[:, k] @ error) / np.sqrt(fit.tip_modes[:, k] @ fit.tip_covariance @ fit.tip_modes[:, k])
                  for k in range(len(fit.modes))]
        print(f"{b:8s}  {len(fit.modes):5d}  {np.array2string(fit.information[:4], precision=1):32s} {ratio:10.3f}"
              f"  {plane_error / floor:6.1f} ({plane_error:.2e})           {np.array2string(np.array(pinned), precision=2)}")
        k_norm = np.hypot(*fit.k_local.T)
        print(f"          |K| across the detector: {np.ptp(k_norm) / k_norm.mean():.1e} peak to peak, "
              f"{np.std(k_norm) / k_norm.mean():.1e} rms (relative)")
        products[b] = fringes.solution_dataset(solution, manifest.detector, fibers=bench.baseline_fibers[b])
    pairs = {}
    for pair, (first, second) in manifest.pairs.items():
        offsets = deprojection.offsets_dataset(products[first], products[second], label=pair)
        good = np.isfinite(offsets["dx"].values)
        n = int(good.sum())
        modes = np.concatenate([offsets["unobservable_dx"].values[:, good], offsets["unobservable_dy"].values[:, good]], 1)
        basis = np.vstack([deprojection._affine_fields(*np.nonzero(good)), modes])
        true = remove_modes(np.concatenate([truth["dx"].values[good], truth["dy"].values[good]]), basis)
        error = np.concatenate([offsets["dx"].values[good], offsets["dy"].values[good]]) - true
        print(f"{pair}: {modes.shape[0]} modes; dx error / floor {rms(error[:n]) / rms(offsets['dx_photon_noise_floor'].values[good]):.3f}, "
              f"dy {rms(error[n:]) / rms(offsets['dy_photon_noise_floor'].values[good]):.3f}")
        pairs[pair] = offsets
    a, b = pairs.values()
    ddx, ddy, _, _ = deprojection.pair_difference(a["dx"].values, a["dy"].values, b["dx"].values, b["dy"].values,
                                                  modes=[(p["unobservable_dx"].values, p["unobservable_dy"].values)
                                                         for p in (a, b)])
    for name, values in (("dx", ddx), ("dy", ddy)):
        floor = rms(np.hypot(a[f"{name}_photon_noise_floor"].values, b[f"{name}_photon_noise_floor"].values)
                    [np.isfinite(values)])
        print(f"pair difference {name}: {rms(values):.3e} pixel rms, floor {floor:.3e} ({rms(values) / floor:.3f}x)")
    good = np.isfinite(a["dx"].values) & np.isfinite(b["dx"].values)
    spaces = [np.linalg.qr(np.concatenate([p["unobservable_dx"].values[:, good], p["unobservable_dy"].values[:, good]],
                                          1).T)[0] for p in (a, b)]
    print("cosines of the principal angles between the pairs' mode spaces:",
          np.array2string(np.linalg.svd(spaces[0].T @ spaces[1], compute_uv=False), precision=4))
    rows, cols = (v.ravel() for v in np.indices(cfg.detector.shape))
    for b in solutions:
        phase, gx, gy = two_source_phase(cols, rows, *(tips[f] for f in bench.baseline_fibers[b]),
                                         wavelength=bench.wavelength, pixel_pitch=bench.pixel_pitch)
        departure = remove_modes(phase, geometry.affine_basis(cols, rows)) / np.hypot(gx, gy).mean()
        print(f"{b}: departure from the best plane over the whole 80x84 detector {rms(departure):.2e} pixel rms "
              f"(midpoint {np.hypot(*BASELINES[b]['midpoint']) * 1e3:.1f} mm off the normal)")


if __name__ == "__main__":
    main()
