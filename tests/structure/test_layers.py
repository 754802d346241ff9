"""The package's import graph points down and has no circles.

Layers, top to bottom: cli -> demo -> monitor/identify/fleet -> link/vision/importers/policy
(where data enters) -> envs -> model (with prediction, profiles) -> io (with plots) ->
units/errors. A module may import from its own layer or any layer below; an import that reaches
up, or a circle between modules (imports inside functions included: they form a circle just the
same when they run), fails.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[2] / "mecanum_hil"

# higher number = higher layer; a module's layer is that of its first-level sub-package/module
LAYERS = {
    "__main__": 10, "cli": 9, "demo": 8,
    "monitor": 7, "identify": 7, "fleet": 7,
    "link": 6, "vision": 6, "importers": 6, "policy": 6,
    "envs": 5,
    "model": 4, "prediction": 4, "profiles": 4,
    "io": 3, "plots": 3,
    "units": 1, "errors": 1, "_jit": 1, "_cores": 1, "__init__": 0, "_version": 0,
}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports(path: Path, name: str) -> set[str]:
    """Every mecanum_hil module ``path`` imports, anywhere in the file."""
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if not target.startswith("mecanum_hil"):
                continue
            # ``from pkg import sub``: the edge goes to the sub-module when it is one
            for alias in node.names:
                sub = f"{target}.{alias.name}"
                found.add(sub if _exists(sub) else target)
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.startswith("mecanum_hil"))
    return found


def _exists(name: str) -> bool:
    rel = Path(*name.split("."))
    root = PACKAGE.parent
    return (root / rel).with_suffix(".py").is_file() or (root / rel / "__init__.py").is_file()


def _graph() -> dict[str, set[str]]:
    graph = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        name = _module_name(path)
        graph[name] = {t for t in _imports(path, name) if t != name}
    return graph


def _layer(name: str) -> int:
    parts = name.split(".")
    key = parts[1] if len(parts) > 1 else "__init__"
    if key not in LAYERS:
        raise AssertionError(f"{name}: sub-package {key!r} has no layer in LAYERS; add it")
    return LAYERS[key]


def test_no_upward_import():
    upward = [
        f"{src} -> {dst}"
        for src, targets in _graph().items()
        for dst in targets
        if _layer(dst) > _layer(src)
    ]
    assert not upward, "imports that reach up a layer:\n" + "\n".join(sorted(upward))


def test_no_circular_import():
    graph = _graph()
    # a package's __init__ re-exports its modules: the edge module -> its own package's
    # __init__ is the usual re-export pattern, only a circle if the __init__ imports it back
    # *and* the module needs the __init__ at import time; we follow edges as written.
    state: dict[str, int] = {}
    stack: list[str] = []
    cycles: list[str] = []

    def visit(node: str) -> None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if nxt not in graph:
                continue
            if state.get(nxt) == 1:
                cycle = [*stack[stack.index(nxt):], nxt]
                if not _package_reexport(cycle):
                    cycles.append(" -> ".join(cycle))
            elif nxt not in state:
                visit(nxt)
        stack.pop()
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            visit(node)
    assert not cycles, "circular imports:\n" + "\n".join(cycles)


def _package_reexport(cycle: list[str]) -> bool:
    """A circle through a package's ``__init__`` that only re-exports its own modules.

    ``pkg/__init__.py`` importing ``pkg.a`` while ``pkg.a`` imports a sibling through ``pkg``
    is resolved by Python in order; it is not one module needing another that needs it.
    """
    packages = [n for n in cycle if (PACKAGE.parent / Path(*n.split(".")) / "__init__.py")
                .is_file()]
    return bool(packages) and all(
        any(m != p and m.startswith(p + ".") for m in cycle) for p in packages
    )


@pytest.mark.parametrize("name", ["mecanum_hil.cli"])
def test_graph_sees_the_cli(name):
    assert name in _graph()
