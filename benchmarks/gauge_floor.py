"""The gauge difference against its measured noise floor: the numbers of docs/metrology.md.

Six noise draws of one baseline (80x84 pixels, 2000 frames in two files, photon and read noise, no PRF width
spread, the true sensitivities as the flat), then three with a chromatic PRNU of 1e-2 and of 5e-2: prints, per
draw, the rms of the
flat gauge's offsets minus the PRNU-free gauge's, its floor from the two halves of the frames, and the
offsets' per-pixel photon floor, all in pixel. Run by hand (about 40 s on 2 cores):

    python benchmarks/gauge_floor.py
"""

import tempfile
from pathlib import Path

import numpy as np

from dice_core import fringe_fit, simulation
from dice_core.io import FrameStream, read_product
from dice_core.manifest import load_manifest


def draw(seed, **metrology):
    cfg = simulation.SimulationConfig.from_dict({
        "name": "gauge-floor", "seed": seed, "frames_per_file": 1000,
        "detector": {"shape": [80, 84], "science_rows": [2, 79], "science_cols": [10, 83], "prf_width_spread": 0.0},
        "dark": {"frames": 2}, "flats": {"frames": 2}, "stars": {"positions": 1, "frames": 1},
        "metrology": {"frames": 2000, "baselines": {"H1H4": {"period": 2.4, "angle_deg": 2.0}}, "pairs": {},
                      **metrology},
    })
    with tempfile.TemporaryDirectory() as folder:
        manifest = load_manifest(simulation.simulate_dataset(cfg, Path(folder)))
        truth = read_product(Path(folder) / "truth.nc").load()
        solution = fringe_fit.fit_baseline(FrameStream(manifest.baselines["H1H4"], manifest.detector),
                                           truth["bias"].values, detector=manifest.detector,
                                           flat=truth["sensitivity"].values, read_noise=truth["read_noise"].values,
                                           label="H1H4")
    difference = np.sqrt(np.nanmean((solution.offsets - solution.offsets_prnu_free) ** 2))
    return difference, solution.gauge_difference_floor, np.sqrt(np.nanmean(solution.photon_floor**2))


def main():
    print("draw         difference  its floor   ratio   per-pixel photon floor (pixel)")
    rows = [draw(seed) for seed in range(6)]
    for seed, (difference, floor, pixel) in enumerate(rows):
        print(f"seed {seed}       {difference:.2e}    {floor:.2e}    {difference / floor:5.2f}   {pixel:.2e}")
    differences, floors, _ = np.array(rows).T
    print(f"over the six: rms difference / rms floor = {np.sqrt(np.mean(differences**2) / np.mean(floors**2)):.2f}")
    pooled = np.sqrt(np.mean(floors**2))
    for level in (1e-2, 5e-2):
        for seed in range(3):
            difference, floor, _ = draw(seed, chromatic_prnu_rms=level)
            print(f"chromatic PRNU {level:g}, seed {seed}: difference {difference:.2e}, {difference / pooled:.1f}x "
                  f"the pooled floor {pooled:.2e}")


if __name__ == "__main__":
    main()
