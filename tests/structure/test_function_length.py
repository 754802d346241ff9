"""Functions stay short enough to read in one screen.

No function anywhere in the package is longer than :data:`MAX_LINES` lines, except the
numba-compiled kernels (a ``jit``/``njit`` decorator), whose loops are kept whole for the
compiler. A command-line command (a function registered in ``mecanum_hil.cli``) is at most
:data:`MAX_COMMAND_LINES` lines: it parses and checks its options, calls the library and prints
the result; the work is in named helpers. A function's length is the whole ``def``, signature
and docstring included, decorators not: ``end_lineno - lineno + 1``. Each offender is reported
with its file, line and length.
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[2] / "mecanum_hil"
REPO = PACKAGE.parent

#: Longest function anywhere in the package [lines].
MAX_LINES = 80
#: Longest command function of the command line [lines].
MAX_COMMAND_LINES = 60
#: Decorators that mark a numba-compiled kernel (also called: ``@njit(cache=True)``).
JIT_DECORATORS = {"jit", "njit"}
#: Functions that run a whole command on their own though not registered as one, by file.
HANDED_COMMANDS = {"cli/_record_policy.py": {"record_policy"}}  # ``record --policy``


def _length(node: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    return node.end_lineno - node.lineno + 1


def _decorator_name(node: ast.expr) -> str:
    if isinstance(node, ast.Call):
        node = node.func
    if isinstance(node, ast.Attribute):
        return node.attr
    return node.id if isinstance(node, ast.Name) else ""


def _is_jit(node: ast.FunctionDef | ast.AsyncFunctionDef) -> bool:
    return any(_decorator_name(d) in JIT_DECORATORS for d in node.decorator_list)


def _functions(path: Path):
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            yield node


def _where(path: Path, node: ast.AST) -> str:
    return f"{path.relative_to(REPO)}:{node.lineno}"


def _command_functions() -> dict[Path, set[str]]:
    """The command functions by file: those registered in ``mecanum_hil.cli`` (its command
    table) and :data:`HANDED_COMMANDS`."""
    from mecanum_hil.cli import _COMMANDS

    found: dict[Path, set[str]] = {}
    for fn in _COMMANDS.values():
        found.setdefault(Path(fn.__code__.co_filename).resolve(), set()).add(fn.__name__)
    for rel, names in HANDED_COMMANDS.items():
        found.setdefault((PACKAGE / rel).resolve(), set()).update(names)
    return found


def test_the_checks_see_what_they_check():
    commands = _command_functions()
    assert len(commands) >= 19 and all(p.is_relative_to(PACKAGE / "cli") for p in commands)
    jitted = [n for p in PACKAGE.rglob("*.py") for n in _functions(p) if _is_jit(n)]
    assert jitted, "no numba kernel found: does the decorator test still match them?"
    short = ast.parse("@nb.njit(cache=True)\ndef f():\n    pass\n").body[0]
    assert _is_jit(short) and _length(short) == 2  # the decorator not counted


def test_no_function_over_80_lines():
    long = [f"{_where(path, node)} {node.name}: {_length(node)} lines"
            for path in sorted(PACKAGE.rglob("*.py"))
            for node in _functions(path)
            if _length(node) > MAX_LINES and not _is_jit(node)]
    assert not long, (f"functions over {MAX_LINES} lines (split them into named helpers):\n"
                      + "\n".join(long))


def test_command_functions_at_most_60_lines():
    long = []
    for path, names in sorted(_command_functions().items()):
        defs = {n.name: n for n in ast.parse(path.read_text(encoding="utf-8")).body
                if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef)}
        for name in sorted(names):
            assert name in defs, f"{path.relative_to(REPO)}: no top-level function {name}"
            node = defs[name]
            if _length(node) > MAX_COMMAND_LINES:
                long.append(f"{_where(path, node)} {name}: {_length(node)} lines")
    assert not long, (f"command functions over {MAX_COMMAND_LINES} lines (move option "
                      "declarations to Annotated aliases, checks and printing to helpers):\n"
                      + "\n".join(long))
