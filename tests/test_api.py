"""dice_core's public functions: options after the first two arguments are keyword-only."""

import importlib
import inspect
import pkgutil
from pathlib import Path

import dice_core

#: Functions whose third and later arguments are data of the same kind as the first two, passed as a
#: group (a pair of fiber tips as ``*tips``, the x and y of a point or of the offsets), or that forward
#: extra positional arguments (``map_lanes``), and the passes of the Allan and fringe reductions that
#: another change splits. Each is a deliberate exception, not a default.
EXCEPTIONS = {
    "allan.batch_offsets", "allan.group_fits", "allan.allan_dataset",
    "centroids.offset_corrected", "deprojection.deproject", "deprojection.pair_difference",
    "deprojection.deproject_floor", "fringes.projected_offsets", "fringes.perfect_pixel_design",
    "geometry.two_source_phase", "geometry.tip_jacobian", "geometry.fit_two_source", "parallel.map_lanes",
    "studies.affine_free",
    # data of one kind passed as a group: the window's offsets and PRF variances, a pixel list's values and
    # coordinates, the Allan statistics' per-pixel arrays, the pose model's directions, poses and bench
    "centroids.response_corrected", "prf.log_transfer", "prf.pixel_scale", "allan.allan_statistics",
    "allan.statistics_dataset", "superimposition.pose_project",
    # stray light: a map's values at pixel coordinates x, y; a component's frequency, chirp and phase (and the
    # reference pixel they are measured from); a baseline's two fiber tips and the stray sources
    "stray_light.canonical", "stray_light.component_design", "stray_light.component_model",
    "stray_light.component_phase", "stray_light.diagnose", "stray_light.diagnosis_variables",
    "stray_light.fit_amplitudes", "stray_light.fringe_terms", "stray_light.quadratic_frequency",
    "stray_light.tangent_modes",
    # a dotted key, the value to set there and the value it replaces
    "overrides.typed_value",
}


def public_functions():
    for info in pkgutil.iter_modules(dice_core.__path__):
        module = importlib.import_module(f"dice_core.{info.name}")
        for name, function in vars(module).items():
            if not name.startswith("_") and inspect.isfunction(function) and function.__module__ == module.__name__:
                yield f"{info.name}.{name}", function


def test_options_after_the_first_two_arguments_are_keyword_only():
    positional = {name for name, function in public_functions()
                  if sum(p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)
                         for p in inspect.signature(function).parameters.values()) > 2}
    assert positional - EXCEPTIONS == set()
    assert EXCEPTIONS - positional == set()  # an exception that no longer is one leaves the list


def test_every_module_is_named_in_the_package_s_docstring_and_the_layout_page():
    """The lists of modules are kept by hand: this keeps them complete."""
    import dice_core

    page = (Path(__file__).resolve().parents[1] / "docs" / "layout.md").read_text()  # the README's layout page
    layout = next(line for line in page.splitlines() if line.startswith("| `dice_core/` |"))
    for module in sorted(Path(dice_core.__file__).parent.glob("*.py")):
        if module.stem != "__init__":
            assert f":mod:`dice_core.{module.stem}`" in dice_core.__doc__, module.stem
            assert f"`{module.stem}`" in layout, module.stem
