"""dice_core.settings: the configuration's schema with the library's choices, its checks, a step's share of it."""

import pytest

from dice_core import centroids, settings, superimposition

from conftest import REPO

SCHEMA = settings.config_schema(REPO / "workflow" / "schemas" / "config.schema.yaml")


def test_the_schema_takes_its_choices_and_their_defaults_from_the_library_s_tables():
    centroid = SCHEMA["properties"]["centroids"]["properties"]
    assert centroid["modes"]["items"]["enum"] == list(centroids.MODES) == centroid["modes"]["default"]
    assert centroid["method"]["enum"] == list(centroids.METHODS) == centroid["methods"]["default"]
    options = SCHEMA["properties"]["astrometry"]["properties"]["superimposition"]["oneOf"]
    assert options[0]["enum"] == list(superimposition.SUPERIMPOSITIONS)
    config = settings.with_defaults({"dataset": "ci"}, SCHEMA)
    assert config["centroids"]["modes"] == list(centroids.MODES) and config["metrology"]["tolerance"] == 1e-7
    assert settings.problems(config, SCHEMA) == []


def test_a_list_whose_order_means_nothing_is_the_same_configuration_in_any_order():
    """centroids.methods (x-dice-unordered) comes out of the check in the library's order whatever order it was
    written in: what the steps read and are re-run by does not follow it; centroids.modes keeps its order."""
    names = list(centroids.METHODS)
    assert len(names) >= 2
    for methods in (names[::-1], names):
        config = settings.checked({"dataset": "ci", "centroids": {"methods": methods, "modes": ["flat", "raw"]}},
                                  SCHEMA)
        assert config["centroids"]["methods"] == names
        assert config["centroids"]["modes"] == ["flat", "raw"]
    one = settings.checked({"dataset": "ci", "centroids": {"methods": names[-1:]}}, SCHEMA)
    assert one["centroids"]["methods"] == names[-1:]


def test_a_list_marked_unordered_without_choices_is_a_schema_error(tmp_path):
    """x-dice-unordered puts a list in its choices' order: a list without choices could not be, and would be left
    as written without a word; the schema is refused instead."""
    schema = tmp_path / "schema.yaml"
    schema.write_text("properties:\n  names:\n    type: array\n    items: {type: string}\n    x-dice-unordered: true\n")
    with pytest.raises(ValueError, match="x-dice-unordered on a list whose items have no x-dice-choices"):
        settings.config_schema(schema)


@pytest.mark.parametrize("values, expected", [
    ({"centroids": {"half_sise": 4}}, "config centroids.half_sise: unknown key; did you mean centroids.half_size?"),
    ({"centroids": {"modes": ["raw", "flat+metrologi"]}}, "config centroids.modes.1: 'flat+metrologi' is not one of"),
    ({"astrometry": {"groups": "many"}}, "config astrometry.groups: 'many' is not of type 'integer'"),
    ({"prnu": {"gradient_degree": 3, "order": 2}}, "config prnu.order: unknown key"),
])
def test_each_problem_is_one_line_naming_the_key(values, expected):
    problems = settings.problems(settings.typed({"dataset": "ci", **values}, SCHEMA), SCHEMA)
    assert len(problems) == 1 and problems[0].startswith(expected), problems


def test_a_mapping_from_the_command_line_is_typed_as_the_schema_says():
    """Snakemake reads --config 'prnu={gradient_degree: 3}' with every value a string."""
    given = {"dataset": "ci", "prnu": {"gradient_degree": "3"},
             "metrology": {"tolerance": "1e-8", "split": "true", "max_passes": "4"},
             "centroids": {"pair": "null", "modes": ["raw", "flat"], "half_size": "x"},
             "astrometry": {"positions": "[25, 57]", "superimposition": ["procrustes", "pose"]}}
    typed = settings.typed(given, SCHEMA)
    assert typed["prnu"]["gradient_degree"] == 3 and typed["metrology"]["tolerance"] == 1e-8
    assert typed["metrology"]["split"] is True and typed["metrology"]["max_passes"] == 4
    assert typed["centroids"]["pair"] is None and typed["centroids"]["modes"] == ["raw", "flat"]
    assert typed["astrometry"]["positions"] == [25, 57]
    assert typed["centroids"]["half_size"] == "x"  # spells no integer: left for the check to name
    assert settings.problems(typed, SCHEMA) == ["config centroids.half_size: 'x' is not of type 'integer'"]
    assert typed["dataset"] == "ci"  # a string stays one


def test_select_keeps_exactly_the_keys_asked_for():
    config = {"chunk_frames": "auto", "prnu": {"gradient_degree": 1}, "metrology": {"tolerance": 1e-7, "parts": 2},
              "sweeps": {"a": {"study": "x", "options": {"n": 1}}, "b": {"study": "y"}}}
    assert settings.select(config, ["metrology.parts", "chunk_frames"]) == {"metrology": {"parts": 2},
                                                                            "chunk_frames": "auto"}
    assert settings.select(config, ["sweeps.{sweep}.options"], sweep="a") == {"sweeps": {"a": {"options": {"n": 1}}}}
    with pytest.raises(KeyError, match="config has no key metrology.nope"):
        settings.select(config, ["metrology.nope"])
    assert settings.leaf_keys({"properties": {"a": {"type": "integer"}, "b": {"properties": {"c": {}}}}}) == ["a",
                                                                                                              "b.c"]
