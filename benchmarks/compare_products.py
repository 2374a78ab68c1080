"""Do the products of the metrology stage change with the code? This tree's against another commit's.

After ``workflow_metrology.py`` has reduced its 200,000-frame baseline with this
tree, this reruns the fringe fit and the Allan step of another dice_core (a
``git archive`` of a commit, unpacked at --old-code) on the same files, in one
process, and prints the largest differences in units of the photon floors:

    mkdir -p /tmp/old && git archive b2ddfdf dice_core | tar -x -C /tmp/old
    python benchmarks/compare_products.py --old-code /tmp/old --workdir /tmp/dice-workflow-bench

(run from outside the repository's root, or the current dice_core shadows the old one).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--old-code", type=Path, required=True, help="folder holding the other dice_core/")
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/dice-workflow-bench"))
    parser.add_argument("--frames", type=int, default=200000)
    args = parser.parse_args()
    sys.path.insert(0, str(args.old_code.resolve()))
    import numpy as np

    import dice_core
    from dice_core import allan, fringe_fit, fringes, io
    from dice_core.manifest import load_manifest

    if not Path(dice_core.__file__).resolve().is_relative_to(args.old_code.resolve()):
        sys.exit(f"imported {dice_core.__file__}, not the old code: run from another folder")
    data = args.workdir / f"n{args.frames}"
    products = data / "results" / "workflow-bench"
    manifest = load_manifest(data / "dataset.yaml")
    dark = io.read_product(products / "calibration/dark.nc")
    prnu = io.read_product(products / "calibration/prnu.nc")
    stream = io.FrameStream(manifest.baselines["H1H4"], manifest.detector, dtype="float32")
    solution = fringe_fit.fit_baseline(stream, dark["dark"].values, detector=manifest.detector,
                                       flat=prnu["prnu"].values, read_noise=dark["noise"].values, workers=2)
    old = fringes.solution_dataset(solution, manifest.detector)
    new = io.read_product(products / "metrology/H1H4.nc")
    floor = float(new["photon_noise_floor_rms"])
    diff = float(np.nanmax(np.abs(old["projected_offset"].values - new["projected_offset"].values)))
    print(f"projected offsets: largest difference {diff:.2e} pixel, {diff / floor:.2e} of the photon floor "
          f"({floor:.2e} pixel)")
    old_allan = allan.allan_of_baseline(stream, new, dark=dark, detector=manifest.detector)
    new_allan = io.read_product(products / "allan/H1H4.nc")
    limit = float(new_allan["photon_limit_pixel"].min())
    for name in ("deviation_mean", "allan_deviation_mean", "photon_limit_pixel", "deviation_block_mean"):
        d = float(np.max(np.abs(old_allan[name].values - new_allan[name].values)))
        print(f"{name}: largest difference {d:.2e} pixel, {d / limit:.2e} of the smallest photon limit")
    d = float(np.nanmax(np.abs(old_allan["batch_offset"].values - new_allan["batch_offset"].values)))
    print(f"batch offsets: largest difference {d:.2e} pixel")


if __name__ == "__main__":
    main()
