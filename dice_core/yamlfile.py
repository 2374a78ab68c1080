"""YAML files read strictly: a key given twice in one mapping is an error, not a silent override.

PyYAML keeps the last of two equal keys. In a dataset manifest that let a
second ``H1H4:`` holding another baseline's files replace the first without a
word, and the run reduced the wrong data with exit status 0. Every YAML file
the project reads (manifests, simulation presets, workflow configuration
files) goes through :func:`load`, which names the key, its path and both lines.
"""

from __future__ import annotations

from pathlib import Path

import yaml

from dice_core import DatasetError

__all__ = ["duplicate_keys", "load", "read"]

_MERGE = "tag:yaml.org,2002:merge"


def _key(loader, node):
    """A mapping key as YAML reads it (``1`` and ``0x1``, ``yes`` and ``true``, ``~`` and ``null`` are one
    key), or its text where it is not a hashable value (a sequence as a key)."""
    try:
        value = loader.construct_object(node, deep=True)
        hash(value)
        return type(value), value
    except (yaml.YAMLError, TypeError):
        return "text", yaml.serialize(node).strip()


def duplicate_keys(node: yaml.Node, where: tuple = (), *, loader=None, seen_nodes=None) -> list[str]:
    """Every key given twice in one mapping of a composed YAML document, as one line each.

    Keys are compared as YAML reads them (``1`` and ``"1"`` differ, ``1`` and ``0x1`` do not); a merge key
    (``<<``) is YAML's own way to override and is not counted. A node an alias repeats is walked once, so
    that nested aliases (a "billion laughs" document) cost no more than the text. Lines count from 1.
    """
    loader = loader or yaml.SafeLoader("")
    seen_nodes = set() if seen_nodes is None else seen_nodes
    if id(node) in seen_nodes:
        return []
    seen_nodes.add(id(node))
    found = []
    if isinstance(node, yaml.MappingNode):
        seen = {}
        for key, value in node.value:
            if key.tag == _MERGE:
                continue
            name = key.value if isinstance(key, yaml.ScalarNode) else yaml.serialize(key).strip()
            identity = _key(loader, key)
            path = ".".join(str(part) for part in (*where, name))
            if identity in seen:
                found.append(f"key {path} is given twice (lines {seen[identity] + 1} and "
                             f"{key.start_mark.line + 1}); YAML would keep the second silently")
            else:
                seen[identity] = key.start_mark.line
            found += duplicate_keys(value, (*where, name), loader=loader, seen_nodes=seen_nodes)
    elif isinstance(node, yaml.SequenceNode):
        for index, item in enumerate(node.value):
            found += duplicate_keys(item, (*where, index), loader=loader, seen_nodes=seen_nodes)
    return found


def load(text: str, source):
    """The YAML document in ``text`` (``source`` names it in errors), refused if a mapping repeats a key.

    Raises
    ------
    DatasetError
        ``source``: not valid YAML (with the line and column), or a key given twice (its path and lines).
    """
    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError as exc:
        raise DatasetError(source, f"not valid YAML ({' '.join(str(exc).split())})") from None
    if node is None:
        return None
    repeated = duplicate_keys(node)
    if repeated:
        more = f" (and {len(repeated) - 1} more)" if len(repeated) > 1 else ""
        raise DatasetError(source, repeated[0] + more)
    return yaml.safe_load(text)


def read(path):
    """The YAML document of the file ``path``, read with :func:`load`; an unreadable file is a DatasetError."""
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(path, f"cannot be read ({exc})") from None
    return load(text, path)
