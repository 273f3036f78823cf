"""YAML graph files with line numbers.

PyYAML's composer keeps the position of every node; we keep those marks beside the plain
data so that pydantic and structural errors can be reported at the exact key.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml
from pydantic import ValidationError

from .diagnostics import Diagnostic, GraphError, Severity, did_you_mean
from .spec import GraphSpec

Path_ = tuple[str | int, ...]


class Locations:
    """Maps key paths such as ``("nodes", "cam", "params")`` to 1-based (line, column)."""

    def __init__(self, file: str) -> None:
        self.file = file
        self._marks: dict[Path_, tuple[int, int]] = {}

    def add(self, path: Path_, mark: yaml.Mark) -> None:
        self._marks.setdefault(path, (mark.line + 1, mark.column + 1))

    def of(self, path: Path_) -> tuple[int, int]:
        """The position of ``path``, or of its nearest located parent."""
        p = tuple(path)
        while p:
            if p in self._marks:
                return self._marks[p]
            p = p[:-1]
        return self._marks.get((), (1, 1))

    def diag(self, path: Path_, message: str, severity: Severity = Severity.error) -> Diagnostic:
        line, col = self.of(path)
        key = ".".join(str(p) for p in path)
        return Diagnostic(severity, message, key=key, file=self.file, line=line, column=col)


def _construct(node: yaml.Node, path: Path_, locs: Locations, errors: list[Diagnostic]) -> Any:
    locs.add(path, node.start_mark)
    if isinstance(node, yaml.MappingNode):
        out: dict[Any, Any] = {}
        for key_node, value_node in node.value:
            key = yaml.SafeLoader.construct_scalar(yaml.SafeLoader(""), key_node)  # type: ignore[arg-type]
            if key_node.tag.endswith(":int"):
                key = int(key)
            child = (*path, key)
            if key in out:
                m = key_node.start_mark
                errors.append(
                    Diagnostic(
                        Severity.error,
                        f"duplicate key {key!r} (first defined on line {locs.of(child)[0]})",
                        key=".".join(str(p) for p in child),
                        file=locs.file,
                        line=m.line + 1,
                        column=m.column + 1,
                    )
                )
                continue
            # A key's position is where the key is written; the value keeps its own below it.
            locs.add(child, key_node.start_mark)
            out[key] = _construct(value_node, child, locs, errors)
        return out
    if isinstance(node, yaml.SequenceNode):
        return [_construct(v, (*path, i), locs, errors) for i, v in enumerate(node.value)]
    loader = yaml.SafeLoader("")
    try:
        return loader.construct_object(node, deep=True)
    finally:
        loader.dispose()


def parse_yaml(text: str, file: str = "<graph>") -> tuple[Any, Locations, list[Diagnostic]]:
    """Parse YAML into plain data plus locations; syntax errors become diagnostics."""
    locs = Locations(file)
    errors: list[Diagnostic] = []
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.MarkedYAMLError as e:
        mark = e.problem_mark or e.context_mark
        line, col = (mark.line + 1, mark.column + 1) if mark else (0, 0)
        msg = f"YAML syntax: {e.problem or e.context}"
        return None, locs, [Diagnostic(Severity.error, msg, file=file, line=line, column=col)]
    if root is None:
        return None, locs, [Diagnostic(Severity.error, "empty graph file", file=file, line=1, column=1)]
    data = _construct(root, (), locs, errors)
    return data, locs, errors


def _known_fields(model_path: Path_) -> list[str]:
    """Field names valid at a location, for 'did you mean' on unknown keys."""
    from .spec import FrameTrigger, InputTrigger, NodeSpec, RestartPolicy, TimerTrigger

    n = len(model_path)
    if n == 0:
        return list(GraphSpec.model_fields)
    if model_path[0] == "nodes":
        if n == 2:
            return list(NodeSpec.model_fields)
        if n == 3 and model_path[2] == "trigger":
            return [*FrameTrigger.model_fields, *TimerTrigger.model_fields, *InputTrigger.model_fields, "loop"]
        if n == 3 and model_path[2] == "restart":
            return list(RestartPolicy.model_fields)
        if n == 4 and model_path[2] == "inputs":
            return ["from", "policy", "size"]
    return []


def pydantic_diagnostics(exc: ValidationError, locs: Locations, prefix: Path_ = ()) -> list[Diagnostic]:
    """Turn pydantic's errors into located diagnostics, with 'did you mean' for unknown keys."""
    out: list[Diagnostic] = []
    for err in exc.errors():
        # Drop discriminator tags pydantic inserts between the field and its members.
        path: Path_ = (*prefix, *_strip_tags(err["loc"]))
        msg = err["msg"]
        if err["type"] == "extra_forbidden":
            key = str(path[-1])
            msg = f"unknown field {key!r}" + did_you_mean(key, _known_fields(path[:-1]))
        elif err["type"] == "missing":
            msg = f"missing required field {str(path[-1])!r}"
        out.append(locs.diag(path, msg))
    return out


def _strip_tags(loc: tuple[Any, ...]) -> tuple[Any, ...]:
    out: list[Any] = []
    for i, p in enumerate(loc):
        is_tag = (
            i > 0
            and loc[i - 1] == "trigger"
            and p in ("frame", "timer", "input", "loop")
            and i + 1 < len(loc)
        )
        if not is_tag:
            out.append(p)
    return tuple(out)


def load_text(text: str, file: str = "<graph>") -> tuple[GraphSpec, Locations]:
    """Parse and validate a graph's text; raises GraphError listing every problem."""
    data, locs, errors = parse_yaml(text, file)
    if data is None:
        raise GraphError(errors)
    if not isinstance(data, dict):
        raise GraphError([*errors, locs.diag((), "a graph file is a mapping with a 'nodes' key")])
    try:
        spec = GraphSpec.model_validate(data)
    except ValidationError as e:
        raise GraphError([*errors, *pydantic_diagnostics(e, locs)]) from None
    if errors:
        raise GraphError(errors)
    return spec, locs


def load_file(path: str | Path) -> tuple[GraphSpec, Locations]:
    """Read a graph file; a missing or unreadable file is a GraphError too, not a traceback."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as e:
        raise GraphError([Diagnostic(Severity.error, f"cannot read graph file: {e.strerror}", file=str(p))]) from None
    except UnicodeDecodeError:
        raise GraphError([Diagnostic(Severity.error, "graph file is not UTF-8 text", file=str(p))]) from None
    return load_text(text, str(p))
