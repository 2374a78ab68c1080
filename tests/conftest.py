"""Shared fixtures: small simulated datasets with known truth; the workflow run in a copy of the repository."""

import copy
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from dice_core import simulation
from dice_core.manifest import load_manifest

# tests/cluster/slurm.sh is opt-in (it installs and starts a SLURM cluster): never collected
collect_ignore = ["cluster"]

REPO = Path(__file__).resolve().parents[1]


def snakemake(workdir, *args, check=True, timeout=1800, cores=2):
    """The README's command (``python -m snakemake --cores 2``, or another number of ``cores``) with ``args``, run
    in ``workdir``, its own dice_core first on the path; a failure is an AssertionError showing the end of what
    it said. The timeout (s) only stops a hung run: the ci run takes 2-3 min on idle cores, and 600 s cut it
    short at load 11-16."""
    env = {**os.environ, "PYTHONPATH": str(workdir)}
    cmd = [sys.executable, "-m", "snakemake", "--cores", str(cores), *args]
    result = subprocess.run(cmd, cwd=workdir, env=env, capture_output=True, text=True, timeout=timeout)
    if check and result.returncode != 0:
        raise AssertionError(f"{' '.join(cmd)} failed:\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}")
    return result


def copy_repository(root):
    """A copy of the workflow and its dice_core in the folder ``root``, for a test to run (and edit)."""
    root.mkdir(parents=True, exist_ok=True)
    for item in ("Snakefile", "workflow", "config", "profiles", "dice_core"):
        source = REPO / item
        if source.is_dir():
            shutil.copytree(source, root / item, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy(source, root / item)
    return root


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


def renamed(document, key, name):
    """A manifest (small_config's layout, the ci preset's) with the dataset, or its second flat, baseline or
    pair, given ``name``."""
    document = copy.deepcopy(document)
    if key == "name":
        document["name"] = name
    elif key == "flat":
        document["flats"][name] = document["flats"].pop("fiber_b")
    elif key == "baseline":
        document["metrology"]["baselines"][name] = document["metrology"]["baselines"].pop("H2H4")
        document["metrology"]["pairs"]["P24"][0] = name
    else:
        document["metrology"]["pairs"][name] = document["metrology"]["pairs"].pop("P24")
    return document


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
