"""dice_core.yamlfile: YAML read strictly, a key given twice refused wherever it is."""

import pytest

from dice_core import DatasetError, yamlfile


@pytest.mark.parametrize("text, expected", [
    ("a: 1\na: 2\n", "key a is given twice (lines 1 and 2)"),
    ("a:\n  b: 1\n  c: 2\n  b: 3\n", "key a.b is given twice (lines 2 and 4)"),
    ("a:\n  - {x: 1, x: 2}\n", "key a.0.x is given twice (lines 2 and 2)"),
    ("'a': 1\na: 2\n", "key a is given twice"),  # quoting does not make another key
    ("1: a\n0x1: b\n", "key 0x1 is given twice (lines 1 and 2)"),  # nor another spelling of the same value
    ("yes: a\ntrue: b\n", "key true is given twice"),
    ("a: 1\na: 1\nb: 1\nb: 2\n", "key a is given twice (lines 1 and 2); YAML would keep the second silently "
                                 "(and 1 more)"),
])
def test_a_repeated_key_is_named_with_its_path_and_lines(text, expected):
    with pytest.raises(DatasetError, match="^config.yaml: " + expected.replace("(", r"\(").replace(")", r"\)")):
        yamlfile.load(text, "config.yaml")


@pytest.mark.parametrize("text, value", [
    ("1: a\n'1': b\n", {1: "a", "1": "b"}),  # an integer and a string are two keys, as YAML reads them
    ("base: &b {x: 1}\nother:\n  <<: *b\n  x: 2\n", {"base": {"x": 1}, "other": {"x": 2}}),  # a merge overrides
    ("", None),
    ("[1, 2]\n", [1, 2]),
])
def test_what_yaml_itself_distinguishes_or_overrides_is_read_as_yaml_reads_it(text, value):
    assert yamlfile.load(text, "f.yaml") == value


def test_invalid_yaml_and_unreadable_files_are_one_line(tmp_path):
    with pytest.raises(DatasetError, match=r"^f.yaml: not valid YAML \(.*line 1, column 4") as info:
        yamlfile.load("a: [1\n", "f.yaml")
    assert "\n" not in str(info.value)
    with pytest.raises(DatasetError, match="cannot be read"):
        yamlfile.read(tmp_path / "missing.yaml")


def test_nested_aliases_are_walked_once(monkeypatch):
    """A "billion laughs" document: 8 levels of 10 aliases, 10^8 leaves if each alias were walked again (34 s
    and growing tenfold a level); each node is walked once."""
    import yaml

    lines = ["l0: &l0 [x, x, x, x, x, x, x, x, x, x]"]
    for level in range(1, 9):
        lines.append(f"l{level}: &l{level} [{', '.join(f'*l{level - 1}' for _ in range(10))}]")
    walked = []
    real = yamlfile.duplicate_keys

    def counted(node, *args, **kwargs):
        walked.append(node)
        return real(node, *args, **kwargs)

    monkeypatch.setattr(yamlfile, "duplicate_keys", counted)
    assert counted(yaml.compose("\n".join(lines) + "\n")) == []
    assert len({id(node) for node in walked}) <= 200 and len(walked) < 200 * 10
