"""Shared fixtures: small simulated datasets with known truth."""

import numpy as np
import pytest
import xarray as xr

from dice_core import simulation
from dice_core.manifest import load_manifest

# tests/cluster/slurm.sh is opt-in (it installs and starts a SLURM cluster): never collected
collect_ignore = ["cluster"]


def small_config(**sections):
    """A small simulated testbed (40x44 pixels); ``sections`` override config sections."""
    values = {
        "name": "sim-test",
        "seed": 11,
        "frames_per_file": 700,
        "detector": {"shape": [40, 44], "science_rows": [2, 39], "science_cols": [3, 43]},
        "dark": {"frames": 100},
        "flats": {"frames": 100},
        "metrology": {"frames": 200, "sweep_frames": 100},
        "stars": {"positions": 3, "frames": 2, "pattern_centre": [23.0, 20.0], "pattern_side": 16.0},
    }
    for key, value in sections.items():
        if isinstance(value, dict):
            values[key] = {**values.get(key, {}), **value}
        else:
            values[key] = value
    return simulation.SimulationConfig.from_dict(values)


@pytest.fixture(scope="session")
def calibration_dataset(tmp_path_factory):
    """Simulated dataset with enough dark and flat frames to test the calibration against truth.

    Returns (manifest, truth). Darks: 5000 frames, so the per-pixel noise
    estimate has a 1% error; flats: 800 frames, in two files each.
    """
    cfg = small_config(dark={"frames": 5000}, flats={"frames": 800}, frames_per_file=500)
    path = simulation.simulate_dataset(cfg, tmp_path_factory.mktemp("calibration") / "raw")
    return load_manifest(path), xr.load_dataset(path.parent / "truth.nc")


@pytest.fixture
def rng():
    return np.random.default_rng(1234)
