"""A step's process imports only what it reaches: the heavy libraries wait for their first use."""

import subprocess
import sys

import pytest
from conftest import REPO

from dice_core import lazy

HEAVY = ("xarray", "pandas", "astropy", "scipy", "netCDF4", "matplotlib", "jsonschema")

CHECK = """
import sys
import dice_core
{imports}
loaded = [name for name in {heavy!r} if name in sys.modules
          and type(sys.modules[name]).__name__ != "_LazyModule"]
print(",".join(loaded))
"""


def loaded_after(imports: str) -> list[str]:
    """The heavy libraries a fresh interpreter has really imported after ``imports``."""
    out = subprocess.run([sys.executable, "-c", CHECK.format(imports=imports, heavy=HEAVY)], check=True,
                         capture_output=True, text=True, cwd=REPO, env={"PYTHONPATH": str(REPO), "PATH": ""})
    return [name for name in out.stdout.strip().split(",") if name]


@pytest.mark.parametrize("imports", [
    "from dice_core import io, stacks\nfrom dice_core.manifest import load_manifest",  # stack_position's
    "from dice_core import centroids, chromatic, io, stacks",  # measure_centroids's
    "from dice_core import calibration, fringe_fit, fringes, io\nfrom dice_core.manifest import load_manifest",  # fit's
    "from dice_core import allan, io\nfrom dice_core.manifest import load_manifest",  # allan_deviation's
    # every module that computes
    "from dice_core import accuracies, allan, calibration, deprojection, error_budget, fringe_fit, fringes, "
    "geometry, prf, reproduction, simulation, stray_light, studies, superimposition",
])
def test_a_step_s_modules_import_no_heavy_library(imports):
    assert loaded_after(imports) == []


def test_a_lazy_module_is_imported_at_its_first_use():
    script = ("from dice_core import stacks\nimport numpy as np\n"
              "stacks.PositionStack(np.zeros((2, 2)), np.zeros((2, 2, 2)), np.zeros((2, 2), int), 4, 1).to_dataset()")
    assert loaded_after(script) == ["xarray", "pandas"]


def test_only_top_level_packages_are_deferred_and_a_missing_one_is_said_at_once():
    with pytest.raises(ValueError, match="top-level"):
        lazy.module("scipy.optimize")
    with pytest.raises(ModuleNotFoundError, match="no_such_package_dice"):
        lazy.module("no_such_package_dice")
    assert lazy.module("sys") is sys
