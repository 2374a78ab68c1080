"""The workflow's configuration: its schema with the choices the library defines, its checks, and each step's
share of it.

The schema (``workflow/schemas/config.schema.yaml``) describes every key with
its type, description and default. Where a key's values are names the library
defines (calibration modes, centroid methods, superimpositions, studies, named spectra), the schema
says ``x-dice-choices: <table>`` instead of listing them, and
:func:`config_schema` fills the enum (and ``x-dice-default: <table>``, a
default of every name) from the table; a list whose order means nothing says ``x-dice-unordered: true``
and :func:`checked` puts it in its table's order, so that its order neither changes a product nor re-runs a
step. The names are listed once, in
:data:`dice_core.centroids.MODES`, :data:`~dice_core.centroids.METHODS`,
:data:`dice_core.superimposition.SUPERIMPOSITIONS`, :data:`dice_core.studies.STUDIES`
(with ``reduction``, the whole workflow per point) and :data:`dice_core.chromatic.SPECTRA`.

A step reads only its own settings (:func:`select`, from the step table
:mod:`dice_core.steps`), which its product records and whose change re-runs
it. Nothing here knows the workflow engine.
"""

from __future__ import annotations

import copy
import difflib
import re
from pathlib import Path

import yaml

from dice_core import lazy
from dice_core.overrides import NUMBER

jsonschema = lazy.module("jsonschema")  # used when a configuration is checked

__all__ = ["choices", "config_schema", "problems", "typed", "with_defaults", "checked", "unordered_in_order",
           "SettingsError", "select", "leaf_keys", "get"]


class SettingsError(ValueError):
    """A configuration the workflow refuses: one line per problem, each naming the key (or the file)."""


def choices() -> dict[str, tuple[str, ...]]:
    """The tables of names a configuration may choose from: {table: names}."""
    from dice_core import centroids, chromatic, studies, superimposition

    return {"modes": tuple(centroids.MODES), "methods": tuple(centroids.METHODS),
            "superimpositions": tuple(superimposition.SUPERIMPOSITIONS), "studies": (*studies.STUDIES, "reduction"),
            "spectra": tuple(chromatic.SPECTRA)}


def config_schema(path) -> dict:
    """The configuration's JSON schema read from ``path``, its ``x-dice-choices`` and ``x-dice-default``
    filled from :func:`choices`."""
    tables = choices()

    def fill(node):
        if isinstance(node, dict):
            if node.get("x-dice-unordered") and "x-dice-choices" not in node.get("items", {}):
                raise ValueError(f"{path}: x-dice-unordered on a list whose items have no x-dice-choices (the order "
                                 f"it is put in): {node.get('description', node)}")
            if "x-dice-choices" in node:
                node["enum"] = list(tables[node["x-dice-choices"]])
            if "x-dice-default" in node:
                node["default"] = list(tables[node["x-dice-default"]])
            for value in node.values():
                fill(value)
        elif isinstance(node, list):
            for value in node:
                fill(value)
        return node

    return fill(yaml.safe_load(Path(path).read_text()))


def problems(values: dict, schema: dict) -> list[str]:
    """Every way ``values`` breaks the schema, one line each naming the key: an unknown key with the nearest
    valid key and the keys of its level (instead of the schema in full), a value with what it should be."""
    validator = jsonschema.validators.validator_for(schema)(schema)
    found = []
    for error in sorted(validator.iter_errors(values), key=lambda e: [str(p) for p in e.absolute_path]):
        where = "".join(f"{part}." for part in error.absolute_path)
        if error.validator == "additionalProperties" and error.validator_value is False:
            known = list(error.schema.get("properties", {}))
            for key in sorted(set(error.instance) - set(known)):
                near = difflib.get_close_matches(str(key), known, n=1, cutoff=0.6)
                hint = f"; did you mean {where}{near[0]}?" if near else ""
                found.append(f"config {where}{key}: unknown key{hint} (keys of {where.rstrip('.') or 'the config'}: "
                             f"{', '.join(known)})")
        else:
            message = error.message if len(error.message) <= 200 else f"{error.message[:200]}..."
            found.append(f"config {where.rstrip('.') or '(top level)'}: {message}")
    return found


def _types(node) -> list:
    kinds = node.get("type", [])
    kinds = [kinds] if isinstance(kinds, str) else list(kinds)
    for option in node.get("oneOf", []) + node.get("anyOf", []):
        kinds += _types(option)
    return kinds


def _typed_string(text: str, kinds: list):
    """``text`` as the first of the schema's ``kinds`` it spells, else itself."""
    lowered = text.strip().lower()
    if "null" in kinds and lowered in ("null", "~", "none", ""):
        return None
    if "boolean" in kinds and lowered in ("true", "false", "yes", "no", "on", "off"):
        return lowered in ("true", "yes", "on")
    if "integer" in kinds and re.fullmatch(r"[+-]?\d+", text.strip()):
        return int(text)
    if ("number" in kinds or "integer" in kinds) and NUMBER.fullmatch(text.strip()):
        number = float(text)
        return int(number) if "number" not in kinds and number.is_integer() else number
    if "array" in kinds and text.strip().startswith("["):
        try:
            return yaml.safe_load(text)
        except yaml.YAMLError:
            return text
    return text


def typed(values, schema: dict):
    """``values`` with every string typed as the schema asks where it spells that type (``"3"`` for an
    integer, ``"1e-8"`` for a number, ``"null"``, ``"true"``): Snakemake reads a mapping given on the command
    line (``--config 'prnu={gradient_degree: 3}'``) with all its values strings. A string that spells no
    allowed type is left for :func:`problems` to name."""
    if isinstance(values, str):
        kinds = _types(schema)
        if "null" in kinds and values.strip().lower() in ("null", "~"):
            return None
        return _typed_string(values, kinds) if kinds and "string" not in kinds else values
    if isinstance(values, dict):
        properties = schema.get("properties", {})
        extra = schema.get("additionalProperties")
        out = {}
        for key, value in values.items():
            child = properties.get(key, extra if isinstance(extra, dict) else {})
            out[key] = typed(value, child)
        return out
    if isinstance(values, list):
        items = schema.get("items", {})
        if not items:  # a list whose schema is one of several options (oneOf)
            items = next((o.get("items", {}) for o in schema.get("oneOf", []) if "items" in o), {})
        return [typed(value, items) for value in values]
    return values


def with_defaults(values: dict, schema: dict) -> dict:
    """A copy of ``values`` with the schema's defaults set wherever a key is absent, at every level."""
    values = copy.deepcopy(values)

    def fill(node, schema_node):
        properties = schema_node.get("properties", {})
        for key, child in properties.items():
            if key not in node and "default" in child:
                node[key] = copy.deepcopy(child["default"])
            if isinstance(node.get(key), dict):
                fill(node[key], child)
        extra = schema_node.get("additionalProperties")
        if isinstance(extra, dict):  # a mapping of names to one kind of entry (config sweeps)
            for key, value in node.items():
                if key not in properties and isinstance(value, dict):
                    fill(value, extra)

    fill(values, schema)
    return values


def checked(values: dict, schema: dict, *, files=()) -> dict:
    """The configuration ``values``, typed as the schema says (a mapping given on the command line arrives as
    strings), checked, with its defaults set. ``files``, the configuration files it was read from, are read
    again strictly: Snakemake's YAML reader keeps the second of a key given twice.

    Raises
    ------
    SettingsError
        Every problem, one line each: a key given twice in a file (its path and lines), an unknown key (with
        the nearest valid one), a value of the wrong type or out of its choices.
    """
    from dice_core import DatasetError, yamlfile

    found = []
    for path in files:
        try:
            yamlfile.read(path)
        except DatasetError as exc:
            found.append(str(exc))
    values = typed(values, schema)
    found += problems(values, schema)
    if found:
        raise SettingsError("\n".join(found))
    return unordered_in_order(with_defaults(values, schema), schema)


def unordered_in_order(values, schema: dict):
    """``values`` with each list the schema marks ``x-dice-unordered`` in the order of its items' choices (their
    enum, :func:`config_schema`), at every level: the same configuration whatever order it was written in."""
    if isinstance(values, dict):
        properties = schema.get("properties", {})
        extra = schema.get("additionalProperties")
        return {key: unordered_in_order(value, properties.get(key, extra if isinstance(extra, dict) else {}))
                for key, value in values.items()}
    if isinstance(values, list) and schema.get("x-dice-unordered"):
        order = schema.get("items", {}).get("enum", [])
        return sorted(values, key=lambda value: order.index(value) if value in order else len(order))
    return values


def leaf_keys(schema: dict, prefix: str = "") -> list[str]:
    """The dotted keys of the schema's leaves (keys whose value is not a mapping of known keys), in order."""
    keys = []
    for key, child in schema.get("properties", {}).items():
        dotted = f"{prefix}{key}"
        if child.get("properties"):
            keys += leaf_keys(child, f"{dotted}.")
        else:
            keys.append(dotted)
    return keys


def get(config: dict, dotted: str):
    """The value of a dotted key; a KeyError names the key."""
    node = config
    for part in dotted.split("."):
        if not isinstance(node, dict) or part not in node:
            raise KeyError(f"config has no key {dotted}")
        node = node[part]
    return node


def select(config: dict, keys, **wildcards) -> dict:
    """The nested part of ``config`` that the dotted ``keys`` name, and nothing else: what a step reads,
    records in its product and is re-run by. A key may hold ``{name}`` fields filled from ``wildcards``
    (``sweeps.{sweep}.options``)."""
    selected = {}
    for key in keys:
        dotted = key.format(**wildcards)
        value = get(config, dotted)
        node = selected
        *parents, last = dotted.split(".")
        for part in parents:
            node = node.setdefault(part, {})
        node[last] = copy.deepcopy(value)
    return selected
