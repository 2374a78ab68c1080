"""PRF width maps on kernels of other shapes (issue 27): the numbers of docs/centroids.md, "PRF widths".

For each PRF shape (truncated hyper-Gaussians of several orders and scales, some asymmetric), an 80x84
detector with a 1% spread of widths and the four baselines of the default bench (plane waves, 4000 frames
each) is simulated and fitted once; its width maps are then made two ways: with the presets' kernel assumed
(order 4, sigma 0.3: what the maps were until issue 27) and over the default family of kernels (orders 2-6,
sigmas 0.25-0.45). Printed per direction, against the truth (its smooth part and mean taken out, as the maps
cannot see them): the ratio of the maps' pixel-to-pixel variations to the truth's, the rms of the difference
over the stated pixel-scale errors, and the mean width against the truth's in its stated error. Run by hand
(about 4 min on 2 shared cores):

    python benchmarks/prf_shapes.py
"""

import sys
import tempfile
from pathlib import Path

import numpy as np

from dice_core import fringe_fit, fringes, prf, simulation
from dice_core.io import FrameStream, read_product
from dice_core.manifest import load_manifest

SHAPES = [(4.0, 0.30, 0.0), (4.0, 0.40, 0.0), (2.0, 0.25, 0.0), (3.0, 0.45, 0.05), (6.0, 0.35, 0.0),
          (5.0, 0.28, 0.05)]  # order, sigma (pixel), slope rms (1/pixel)


def simulate(order, sigma, slope, folder):
    cfg = simulation.SimulationConfig.from_dict({
        "name": "prf-shapes", "frames_per_file": 100000,
        "detector": {"prf_order": order, "prf_sigma": sigma, "prf_slope_rms": slope},
        "dark": {"frames": 2}, "flats": {"frames": 2}, "stars": {"positions": 1, "frames": 1},
        "metrology": {"frames": 4000}})
    manifest = load_manifest(simulation.simulate_dataset(cfg, folder))
    truth = read_product(folder / "truth.nc").load()
    products = {}
    for name, acquisition in manifest.baselines.items():
        solution = fringe_fit.fit_baseline(FrameStream(acquisition, manifest.detector), truth["bias"].values,
                                           detector=manifest.detector, flat=truth["sensitivity"].values,
                                           read_noise=truth["read_noise"].values, label=name, workers=2)
        products[name] = fringes.solution_dataset(solution, manifest.detector)
    return manifest, truth, products


def compare(maps, truth, axis):
    """(variations' ratio, rms difference over the pixel-scale error, mean, the truth's mean, the mean's error)."""
    width = getattr(maps, f"width_{axis}")
    error = getattr(maps, f"error_width_pixel_{axis}", getattr(maps, f"error_width_{axis}"))
    ok = np.isfinite(width)
    rows, cols = np.nonzero(ok)
    mapped, true = (prf.pixel_scale(v, cols, rows, degree=maps.smooth_degree)
                    for v in (width[ok], truth[f"width_{axis}"].values[ok]))
    mean = float(np.mean(width[ok]))
    mean_error = getattr(maps, "error_mean_width", {}).get(axis, 0.0)
    return (np.std(mapped) / np.std(true), float(np.sqrt(np.mean(((mapped - true) / error[ok]) ** 2))), mean,
            float(truth[f"width_{axis}"].values[ok].mean()), mean_error)


def main():
    print("| order, sigma, slopes | true width | maps | axis | variations / truth | difference / error | mean width |")
    print("|---|---:|---|---|---:|---:|---|")
    for order, sigma, slope in SHAPES:
        with tempfile.TemporaryDirectory() as folder:
            manifest, truth, products = simulate(order, sigma, slope, Path(folder))
        options = dict(gain=manifest.detector.gain, read_noise=truth["read_noise"].values,
                       science=manifest.detector.science_mask())
        for label, shape in (("assumed kernel", prf.PrfShape()), ("family", prf.PrfFamily())):
            maps = prf.width_maps(products, shape=shape, **options)
            for axis in "xy":
                ratio, over, mean, true_mean, mean_error = compare(maps, truth, axis)
                print(f"| {order:g}, {sigma:g}, {slope:g} | {true_mean:.4f} | {label} | {axis} | {ratio:.3f} | "
                      f"{over:.2f} | {mean:.4f} +- {mean_error:.4f} |")
        sys.stdout.flush()


if __name__ == "__main__":
    main()
