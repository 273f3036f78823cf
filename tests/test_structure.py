"""The kernel's shape, held by CI: no class over 400 lines, no module over 800, no function
over 120 in flowrt/ (issue 25; trio's ``_core`` and starlette stay readable the same way)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import flowrt

ROOT = Path(flowrt.__file__).parent
LIMITS = {"module": 800, "class": 400, "function": 120}


def _sizes() -> list[tuple[str, str, int]]:
    found = []
    for path in sorted(ROOT.rglob("*.py")):
        src = path.read_text()
        rel = str(path.relative_to(ROOT.parent))
        found.append(("module", rel, len(src.splitlines())))
        for node in ast.walk(ast.parse(src)):
            if isinstance(node, ast.ClassDef):
                kind = "class"
            elif isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                kind = "function"
            else:
                continue
            assert node.end_lineno is not None
            found.append((kind, f"{rel}:{node.name}", node.end_lineno - node.lineno + 1))
    return found


@pytest.mark.parametrize("kind", sorted(LIMITS))
def test_no_part_of_flowrt_is_too_long(kind: str) -> None:
    too_long = [f"{name} ({n} lines)" for k, name, n in _sizes() if k == kind and n > LIMITS[kind]]
    assert not too_long, f"{kind}s over {LIMITS[kind]} lines: " + ", ".join(too_long)


def test_the_measure_sees_the_kernel() -> None:
    """The walk finds what it must judge (a broken walk would pass every limit)."""
    names = {name for _, name, _ in _sizes()}
    assert "flowrt/kernel/runner.py:NodeRunner" in names
    assert "flowrt/kernel/scheduler.py" in names
