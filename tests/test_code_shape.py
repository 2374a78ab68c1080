"""dice_core's functions stay readable at once: none over 100 lines of code, its docstring aside."""

import ast
from pathlib import Path

import dice_core

#: The most lines a function's body may take: from its first statement after the docstring to its last
#: line, blank lines and comments within it included (a reader takes them in with the code). Nested
#: functions and methods count on their own, and within the function that holds them.
MAX_LINES = 100


def body_lines(function: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """Lines of ``function``'s body without its docstring (0 for a docstring alone)."""
    body = function.body
    first = body[0]
    if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str):
        body = body[1:]
    return function.end_lineno - body[0].lineno + 1 if body else 0


def long_functions(path: Path) -> dict:
    """The functions of a module over :data:`MAX_LINES` lines: ``"<file>:<line> <name>"`` -> lines."""
    tree = ast.parse(path.read_text(), filename=str(path))
    return {f"{path.name}:{node.lineno} {node.name}": body_lines(node) for node in ast.walk(tree)
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and body_lines(node) > MAX_LINES}


def test_no_function_of_dice_core_is_over_100_lines_of_code():
    package = Path(dice_core.__file__).parent
    modules = sorted(package.rglob("*.py"))
    assert len(modules) > 20  # the package itself, not an empty folder
    long = {}
    for path in modules:
        long.update(long_functions(path))
    assert long == {}, f"split these into well-named helpers: {long}"


def test_the_count_leaves_out_the_docstring_only(tmp_path):
    path = tmp_path / "module.py"
    lines = "\n".join(f"    x{i} = {i}" for i in range(MAX_LINES))
    path.write_text(f'def short():\n    """A docstring\n\n    of four lines.\n    """\n{lines}\n\n\n'
                    f"async def long():\n{lines}\n    # a comment within counts\n    return x0\n")
    functions = {node.name: body_lines(node) for node in ast.walk(ast.parse(path.read_text()))
                 if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))}
    assert functions == {"short": MAX_LINES, "long": MAX_LINES + 2}
    assert list(long_functions(path).values()) == [MAX_LINES + 2]
