"""The step table against the workflow it describes: each rule is a step, hands its script only the step's
settings, and its code hash follows the script's own imports; every configuration key is read by a step or is a
planning key; names the library defines are listed once."""

import ast
import re

import pytest

from dice_core import centroids, resources, settings, steps

from conftest import REPO

RULES = REPO / "workflow" / "rules"
SCRIPTS = REPO / "workflow" / "scripts"
SCHEMA = settings.config_schema(REPO / "workflow" / "schemas" / "config.schema.yaml")


def rule_blocks():
    """[(rule name, its text)] of every rule of the workflow (``use rule ... as X with:`` included; a rule made
    once per group of star positions, named by ``steps.group_rule("<step>", ...)``, as its step)."""
    text = "\n".join(path.read_text() for path in sorted(RULES.glob("*.smk"))) + "\n" + (REPO / "Snakefile").read_text()
    starts = list(re.finditer(
        r'^\s*(?:rule (\w+):|use rule \w+ as (\w+) with:|rule:\s+name:\s+steps\.group_rule\("(\w+)")', text, re.M))
    return [((m.group(1) or m.group(2) or m.group(3)), text[m.end():(starts[i + 1].start() if i + 1 < len(starts)
                                                                     else len(text))])
            for i, m in enumerate(starts)]


def test_every_rule_is_a_step_and_hands_its_script_the_step_s_params():
    blocks = [(name, block) for name, block in rule_blocks() if name not in ("all", "paper")]
    assert {name for name, _ in blocks} == set(steps.STEPS)
    for name, block in blocks:
        assert re.search(rf'\*\*step_params\(\s*"{name}"', block), f"rule {name} takes no params of its own step"
        assert re.search(rf'step_resources\("{name}"[,)]', block) or name == "measure_centroids_by_method", name
        script = re.search(r'"\.\./scripts/(\w+)\.py"', block)
        if script:
            assert script.group(1) == steps.step(name).script_name, name
    for step in steps.STEPS.values():
        assert (SCRIPTS / f"{step.script_name}.py").is_file(), step.name


def test_no_script_reads_the_whole_configuration_and_no_rule_lists_modules_by_hand():
    for script in SCRIPTS.glob("*.py"):
        assert "snakemake.config" not in script.read_text(), script.name
    for rules in [*RULES.glob("*.smk"), REPO / "Snakefile"]:
        text = rules.read_text()
        assert "code_version(" not in text and "script_version(" not in text, rules.name


def schema_leaf(key):
    """A declared key (``sweeps.{sweep}.options``) as the schema's leaf it names (``sweeps``)."""
    return "sweeps" if key.startswith("sweeps.") else key


def test_every_setting_a_step_declares_is_a_key_of_the_schema_and_every_key_is_read_or_planned():
    leaves = settings.leaf_keys(SCHEMA)
    declared = {schema_leaf(key) for step in steps.STEPS.values() for key in step.settings}
    assert declared <= set(leaves), declared - set(leaves)
    unread = [key for key in leaves if key not in declared and key not in steps.PLANNING_KEYS]
    assert unread == [], f"configuration keys no step reads: {unread}"
    assert not set(steps.PLANNING_KEYS) & {k for s in steps.STEPS.values() for k in s.settings}


def test_a_step_s_settings_are_exactly_its_keys_and_those_of_the_steps_it_stands_for():
    config = settings.with_defaults({"dataset": "ci", "sweeps": {"s": {"study": "tip_tilt", "parameter": "a",
                                                                          "values": [1]}}}, SCHEMA)
    assert settings.select(config, steps.settings_keys("measure_prnu")) == {"chunk_frames": "auto",
                                                                            "prnu": {"gradient_degree": 1}}
    finish = steps.settings_keys("fit_finish")
    assert set(finish) >= {k for name in ("fit_start", "fit_part", "fit_reduce") for k in steps.settings_keys(name)}
    assert settings.select(config, steps.settings_keys("sweep_point"), sweep="s") == {
        "sweeps": {"s": {"study": "tip_tilt", "bench": {}, "options": {}}}}
    with pytest.raises(KeyError, match="no step 'nope'"):
        steps.step("nope")


def dice_core_modules(path):
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module == "dice_core":
            names |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith("dice_core."):
            names.add(node.module.split(".")[1])
    return names


def test_resources_name_steps_of_the_table():
    assert set(resources.COSTS) <= set(steps.STEPS)
    for name, block in rule_blocks():  # a rule whose jobs are benchmarked has a measured cost
        if "benchmark:" in block and name in steps.STEPS and name != "measure_centroids_by_method":
            assert name in resources.COSTS or name in ("prf_widths", "procrustes_deflation"), name


CODE = [*(REPO / "dice_core").glob("*.py"), *RULES.glob("*.smk"), REPO / "Snakefile",
        REPO / "workflow" / "schemas" / "config.schema.yaml", REPO / "config" / "config.yaml"]


def test_modes_methods_and_studies_are_listed_once():
    """The names of dice_core.centroids.MODES and METHODS (and of the studies) appear together only in the
    table that defines them: the schema, the workflow, the studies and the docs take them from it."""
    for path in CODE:
        text = path.read_text()
        if path.name != "centroids.py":
            assert not all(re.search(rf'["\s\[,]{re.escape(m)}["\],\s]', text) for m in centroids.MODES), path
            assert not re.search(r'["\[]fourier["]?,\s*["]?gaussian', text), path
        if path.name != "studies.py":
            assert not re.search(r"offset_bias[\"']?,\s*[\"']?error_propagation[\"']?,\s*[\"']?star_accuracy", text), path


def test_a_step_s_code_is_its_script_s_imports_and_not_the_workflow_s_description():
    """Editing a module re-runs the steps that run it, and only those: the dark does not run the centroids, and
    no step's code is the catalogue, the step table or the settings, which describe the workflow (an edit to
    them, declaring a product or a setting, re-ran all 73 jobs of the ci preset)."""
    def modules(name):
        return steps.code_modules([SCRIPTS / f"{steps.step(n).script_name}.py"
                                   for n in (name, *steps.step(name).stands_for)])

    assert {"io", "calibration", "manifest"} <= modules("measure_dark")
    for name in steps.STEPS:
        assert not modules(name) & steps.DESCRIPTIVE, name
    assert "centroids" not in modules("measure_dark") | modules("simulate_truth")
    assert {"centroids", "stacks"} <= modules("measure_centroids")
    assert {"fringe_fit"} <= modules("fit_finish") and modules("fit_part") <= modules("fit_finish")


def test_a_group_s_rule_names_its_step_and_its_inputs():
    assert steps.group_rule("stack_position", (1, 2, 90)) == "stack_position_1_to_90"
    assert steps.group_rule("simulate_file", (7,)) == "simulate_file_7"
    for rule, step in [("stack_position_1_to_90", "stack_position"), ("simulate_file_7", "simulate_file"),
                       ("simulate_file", "simulate_file"), ("plot_dark", "plot_dark")]:
        assert steps.step_of_rule(rule) == step
    assert steps.rule_group("stack_position_1_to_90") == ("stack_position", 1, 90)
    assert steps.rule_group("simulate_file_7") == ("simulate_file", 7, 7) and steps.rule_group("plot_dark") is None
    assert steps.rule_group("stack_position_9_to_3") is None and steps.rule_group("sweep_a_stack_position_1") is None
    with pytest.raises(KeyError, match="no jobs by groups of inputs"):
        steps.group_rule("plot_dark", (1,))
    for rule in ("plot_dark_3", "stack_position_1_to", "stack_positions_1"):
        with pytest.raises(KeyError, match="no step runs rule"):
            steps.step_of_rule(rule)
