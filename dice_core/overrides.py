"""Dotted-key overrides of nested configurations, one rule for all of them.

The workflow's reduction sweeps (a point's keys on the run's config), the
studies' benches (:func:`dice_core.studies.apply_overrides`) and the
simulation presets (:func:`dice_core.simulation.load_preset`) all set keys
such as ``detector.prnu_rms`` on a nested dict, and all read a string that
YAML 1.1 left unparsed (``2e-3``, with no dot) as the number it spells.
"""

from __future__ import annotations

import copy
import re

import numpy as np

__all__ = ["NUMBER", "apply_dotted", "typed_value"]

#: A number as YAML 1.2 reads one, which YAML 1.1 (PyYAML) leaves a string when it has no dot: 2e-3.
NUMBER = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?")
_INTEGER = re.compile(r"[+-]?\d+")


def typed_value(dotted: str, value, current, *, what: str = "config"):
    """``value`` to set at ``dotted`` where the config holds ``current`` (None where it holds nothing).

    A NumPy scalar becomes its Python value; a string that spells a number
    becomes that number (an int if it has no dot or exponent), unless the
    config holds a string there.

    Raises
    ------
    ValueError
        A string that is not a number where the config holds a number.
    """
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, str) and not isinstance(current, str):
        if NUMBER.fullmatch(value):
            return int(value) if _INTEGER.fullmatch(value) else float(value)
        if isinstance(current, (int, float)) and not isinstance(current, bool):
            raise ValueError(f"{dotted}: {value!r} is not a number, which the {what} expects")
    return value


def apply_dotted(base: dict, overrides: dict, *, new_sections: bool = True, what: str = "config") -> dict:
    """A copy of the nested dict ``base`` with dotted keys set: ``{"detector.prnu_rms": 5e-5}``.

    Values go through :func:`typed_value`. ``new_sections`` creates a section
    that ``base`` lacks; without it, such a key is refused. ``what`` names
    the config in messages.

    Raises
    ------
    KeyError
        A key whose parent is missing (``new_sections`` False) or not a section.
    ValueError
        See :func:`typed_value`.
    """
    out = copy.deepcopy(base)
    for dotted, value in overrides.items():
        *parents, leaf = dotted.split(".")
        node = out
        for part in parents:
            if part not in node and new_sections:
                node[part] = {}
            if not isinstance(node.get(part), dict):
                raise KeyError(f"{dotted}: the {what} has no section {part!r}")
            node = node[part]
        node[leaf] = typed_value(dotted, value, node.get(leaf), what=what)
    return out
