"""The runtime's layering, read from the source: no import circle, the runtime below its users.

Every import counts, wherever it is written: at module level, inside a function (imported
late, but the modules still depend on each other) and under ``if TYPE_CHECKING:`` (a type
names the other module's concept, so a change there breaks this one). The graph is read
with :mod:`ast`, without importing anything, so a circle that Python happens to resolve at
run time is still found.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "flowrt"

#: What the runtime core must never import: its users (monitors, the CLI) and the nodes.
RUNTIME_CORE = ("flowrt.runtime._runtime", "flowrt.kernel", "flowrt.runtime._qos", "flowrt.workers")
USERS = ("flowrt.control.server", "flowrt.monitors.status", "flowrt.cli", "flowrt.nodes")


def module_name(path: Path, root: Path = ROOT) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def modules() -> dict[str, Path]:
    return {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def resolve(current: str, is_package: bool, level: int, name: str | None) -> str:
    """The absolute module a relative ``from`` import names."""
    base = current.split(".")
    if not is_package:
        base = base[:-1]
    if level > 1:
        base = base[: len(base) - (level - 1)]
    return ".".join([*base, *([name] if name else [])])


def imports_of(name: str, path: Path, known: set[str]) -> set[str]:
    """Every flowrt module that ``name`` imports, anywhere in its file."""
    tree = ast.parse(path.read_text(), filename=str(path))
    is_package = path.name == "__init__.py"
    found: set[str] = set()

    def add(target: str) -> None:
        # ``import flowrt.x.y`` depends on flowrt.x.y; a name inside a module on its module.
        while target and target not in known:
            target = target.rpartition(".")[0]
        if target and target != name:
            found.add(target)

    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == "flowrt":
                    add(alias.name)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = resolve(name, is_package, node.level, node.module)
            elif node.module and node.module.split(".")[0] == "flowrt":
                base = node.module
            else:
                continue
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                add(sub if sub in known else base)
    return found


def import_graph() -> dict[str, set[str]]:
    mods = modules()
    known = set(mods)
    return {name: imports_of(name, path, known) for name, path in mods.items()}


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []
    counter = 0

    def visit(v: str) -> None:
        nonlocal counter
        index[v] = low[v] = counter
        counter += 1
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_reader_sees_every_kind_of_import(tmp_path: Path) -> None:
    """The parser itself: module-level, function-level and TYPE_CHECKING imports all count."""
    pkg = tmp_path / "flowrt"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .b import B\n"
    )
    (pkg / "b.py").write_text("def f():\n    from . import c\n")
    (pkg / "c.py").write_text("import flowrt.a\n")
    paths = {module_name(p, tmp_path): p for p in pkg.rglob("*.py")}
    names = set(paths)
    graph = {n: imports_of(n, p, names) for n, p in paths.items() if n != "flowrt"}
    assert graph == {"flowrt.a": {"flowrt.b"}, "flowrt.b": {"flowrt.c"}, "flowrt.c": {"flowrt.a"}}
    assert circles(graph) == [["flowrt.a", "flowrt.b", "flowrt.c"]]


def test_flowrt_has_no_import_circle() -> None:
    found = circles(import_graph())
    assert found == [], "import circles (counting function-level and TYPE_CHECKING imports): " + (
        "; ".join(" <-> ".join(c) for c in found)
    )


@pytest.mark.parametrize("core", RUNTIME_CORE)
def test_the_runtime_does_not_import_its_users(core: str) -> None:
    graph = import_graph()
    assert core in graph
    bad = sorted(m for m in graph[core] if m.startswith(USERS))
    assert bad == [], f"{core} imports {bad}: monitors and the CLI use the runtime, not the reverse"
