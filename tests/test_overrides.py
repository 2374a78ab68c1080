"""Dotted-key overrides: one rule for the workflow's sweeps, the studies' benches and the presets."""

from pathlib import Path

import numpy as np
import pytest

from dice_core import simulation, studies
from dice_core.overrides import apply_dotted, typed_value

PRESETS = Path(__file__).resolve().parents[1] / "config" / "presets"


def test_a_string_that_spells_a_number_is_that_number_unless_the_config_holds_a_string():
    assert typed_value("a", "2e-3", 1.0) == 2e-3 and typed_value("a", "2e-3", None) == 2e-3
    assert typed_value("a", "3", 7) == 3 and type(typed_value("a", "3", 7)) is int
    assert typed_value("a", "2e-3", "name") == "2e-3"  # a string where the config holds one stays a string
    assert typed_value("a", "fourier", None) == "fourier"
    assert type(typed_value("a", np.float64(0.5), 1.0)) is float
    with pytest.raises(ValueError, match="a: 'high' is not a number"):
        typed_value("a", "high", 1.0)


def test_apply_dotted_copies_and_creates_or_refuses_sections():
    base = {"detector": {"prnu_rms": 1e-3}, "seed": 1}
    out = apply_dotted(base, {"detector.prnu_rms": "2e-3", "metrology.frames": "2000"})
    assert out == {"detector": {"prnu_rms": 2e-3}, "seed": 1, "metrology": {"frames": 2000}}
    assert base["detector"]["prnu_rms"] == 1e-3 and "metrology" not in base
    with pytest.raises(KeyError, match="no section 'metrology'"):
        apply_dotted(base, {"metrology.frames": 1}, new_sections=False)
    with pytest.raises(KeyError, match="no section 'seed'"):
        apply_dotted(base, {"seed.value": 1})


def test_the_three_users_read_2e_3_alike():
    bench = studies.apply_overrides(studies.OFFSET_BIAS_BENCH, {"detector.prnu_rms": "2e-3"})
    preset = simulation.load_preset(PRESETS / "ci.yaml", {"detector.prnu_rms": "2e-3"})
    assert bench["detector"]["prnu_rms"] == preset.detector.prnu_rms == 2e-3


def test_preset_overrides_name_another_dataset():
    """The preset's name plus a hash of the overrides (as numbers: 2e-3 and 0.002 are one dataset)."""
    plain = simulation.load_preset(PRESETS / "ci.yaml")
    a = simulation.load_preset(PRESETS / "ci.yaml", {"detector.prnu_rms": "2e-3"})
    b = simulation.load_preset(PRESETS / "ci.yaml", {"detector.prnu_rms": 0.002})
    c = simulation.load_preset(PRESETS / "ci.yaml", {"detector.prnu_rms": 0.003})
    assert plain.name == "sim-ci" and a.name == b.name != c.name and a.name.startswith("sim-ci-")
    assert simulation.load_preset(PRESETS / "ci.yaml", {"name": "mine", "detector.prnu_rms": 0.003}).name == "mine"
    with pytest.raises(ValueError, match="ci.yaml: override"):
        simulation.load_preset(PRESETS / "ci.yaml", {"name.x": 1})
