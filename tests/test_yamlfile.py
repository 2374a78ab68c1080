"""dice_core.yamlfile: YAML read strictly, a key given twice refused wherever it is."""

import pytest

from dice_core import DatasetError, yamlfile


@pytest.mark.parametrize("text, expected", [
    ("a: 1\na: 2\n", "key a is given twice (lines 1 and 2)"),
    ("a:\n  b: 1\n  c: 2\n  b: 3\n", "key a.b is given twice (lines 2 and 4)"),
    ("a:\n  - {x: 1, x: 2}\n", "key a.0.x is given twice (lines 2 and 2)"),
    ("'a': 1\na: 2\n", "key a is given twice"),  # quoting does not make another key
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
