"""YAML graph files with line numbers.

PyYAML's composer keeps the position of every node; we keep those marks beside the plain
data so that pydantic and structural errors can be reported at the exact key.

Every problem is collected rather than raised at the first: YAML-level problems (duplicate
keys, tags), then pydantic's errors; nodes that fail pydantic are set aside so that
the structural checks of :func:`flowrt.graph._resolve.resolve` still run on the rest of the graph.
"""

from __future__ import annotations

import copy
import types
import typing
from collections.abc import Collection, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, Tag, ValidationError

from .diagnostics import Diagnostic, GraphError, Severity, closest, did_you_mean
from .spec import GraphSpec

Path_ = tuple[str | int, ...]

# A file whose aliases expand to more than this many YAML nodes is refused ("billion laughs").
MAX_YAML_NODES = 200_000
# A graph file above this size is refused before it is parsed: a graph of hundreds of nodes
# is tens of kB, and PyYAML reads about 200 kB/s (a 6 MB file took 25 s and 632 MB).
MAX_FILE_BYTES = 256 << 10
# ... and one that writes more values than this (``[1,1,1,...]``) is refused while parsing.
MAX_WRITTEN_VALUES = 50_000

_STANDARD_TAG = "tag:yaml.org,2002:"


def _shown_tag(tag: str) -> str:
    return "!!" + tag[len(_STANDARD_TAG) :] if tag.startswith(_STANDARD_TAG) else tag


def _size_text(n: int) -> str:
    return f"{n / 2**20:.1f} MiB" if n >= 2**20 else f"{n / 2**10:.0f} KiB"


def too_large(size: int, file: str) -> Diagnostic:
    """The one error for a file over :data:`MAX_FILE_BYTES`."""
    return Diagnostic(
        Severity.error,
        f"graph file too large: {_size_text(size)}, the limit is {_size_text(MAX_FILE_BYTES)} "
        "(a graph of hundreds of nodes is tens of kB)",
        file=file,
    )


class _TagRecordingLoader(yaml.SafeLoader):
    """PyYAML's safe loader, noting every node written with an explicit tag.

    The safe constructors refuse ``!!python/...`` on scalars, but on a mapping or sequence
    the tag was silently dropped (``cpus: !!python/object/apply:os.system [1]`` validated as
    ``cpus: [1]``). A graph file is plain data: every tag is reported where it is written.
    """

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self.tagged: dict[int, str] = {}  # id(node) -> the tag as written
        self.written = 0

    def compose_node(self, parent: Any, index: Any) -> Any:
        event = self.peek_event()  # type: ignore[no-untyped-call]
        self.written += 1
        if self.written > MAX_WRITTEN_VALUES:
            raise _TooLarge(aliased=False)
        tag = None if isinstance(event, yaml.AliasEvent) else getattr(event, "tag", None)
        node = super().compose_node(parent, index)
        if tag is not None:
            self.tagged[id(node)] = tag
        return node


class Locations:
    """Maps key paths such as ``("nodes", "cam", "params")`` to 1-based (line, column)."""

    def __init__(self, file: str) -> None:
        self.file = file
        self._marks: dict[Path_, tuple[int, int]] = {}

    def add(self, path: Path_, mark: yaml.Mark) -> None:
        self._marks.setdefault(path, (mark.line + 1, mark.column + 1))

    def of(self, path: Path_) -> tuple[int, int]:
        """The position of ``path``, or of its nearest located parent.

        (0, 0) when nothing is located: a graph built in Python has no file position.
        """
        p = tuple(path)
        while p:
            if p in self._marks:
                return self._marks[p]
            p = p[:-1]
        return self._marks.get((), (0, 0))

    def diag(self, path: Path_, message: str, severity: Severity = Severity.error) -> Diagnostic:
        line, col = self.of(path)
        key = ".".join(str(p) for p in path)
        return Diagnostic(severity, message, key=key, file=self.file, line=line, column=col)


class _Constructor:
    """Plain data from a composed YAML tree, recording every key's position on the way."""

    def __init__(
        self, locs: Locations, errors: list[Diagnostic], tagged: dict[int, str] | None = None
    ) -> None:
        self.locs = locs
        self.errors = errors
        self.loader = yaml.SafeLoader("")
        self.active: set[int] = set()  # collections being built: an alias to one is a cycle
        self.budget = MAX_YAML_NODES
        self.tagged = tagged or {}
        self.seen: set[int] = set()  # nodes built: one built again is an alias expanded
        self.aliased = False

    def _refuse_tag(self, node: yaml.Node, path: Path_) -> bool:
        tag = self.tagged.get(id(node))
        if tag is None:
            return False
        self.error(
            path,
            node.start_mark,
            f"YAML tag {_shown_tag(tag)!r} is not allowed: a graph file is plain data",
        )
        return True

    def error(self, path: Path_, mark: yaml.Mark, message: str) -> None:
        self.errors.append(
            Diagnostic(
                Severity.error,
                message,
                key=".".join(str(p) for p in path),
                file=self.locs.file,
                line=mark.line + 1,
                column=mark.column + 1,
            )
        )

    def build(self, node: yaml.Node, path: Path_) -> Any:
        self.locs.add(path, node.start_mark)
        self.budget -= 1
        if self.budget < 0:
            raise _TooLarge(self.aliased)
        if id(node) in self.seen:
            self.aliased = True
        self.seen.add(id(node))
        if self._refuse_tag(node, path) and isinstance(node, yaml.ScalarNode):
            return node.value  # not constructed: `!!python/...` never runs
        if isinstance(node, yaml.MappingNode | yaml.SequenceNode):
            if id(node) in self.active:
                self.error(path, node.start_mark, "recursive alias: a value contains itself")
                return None
            self.active.add(id(node))
            try:
                if isinstance(node, yaml.SequenceNode):
                    return [self.build(v, (*path, i)) for i, v in enumerate(node.value)]
                return self._mapping(node, path)
            finally:
                self.active.discard(id(node))
        try:
            return self.loader.construct_object(node, deep=True)
        except Exception as e:  # PyYAML's scalar constructors fail in many ways (`!!int` alone)
            problem = getattr(e, "problem", None) or str(e)
            self.error(path, node.start_mark, f"bad value {node.value!r}: {problem}")
            return node.value

    def _mapping(self, node: yaml.MappingNode, path: Path_) -> dict[str | int, Any]:
        out: dict[str | int, Any] = {}
        merged: dict[str | int, Any] = {}
        for key_node, value_node in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                self._merge(value_node, path, merged)
                continue
            if not isinstance(key_node, yaml.ScalarNode):
                self.error(
                    path, key_node.start_mark, "a key must be a plain name, not a list or mapping"
                )
                continue
            key = self._key(key_node)
            child = (*path, key)
            self._refuse_tag(key_node, child)
            if key in out:
                first = self.locs.of(child)[0]
                self.error(
                    child,
                    key_node.start_mark,
                    f"duplicate key {key!r} (first defined on line {first})",
                )
                continue
            # A key's position is where the key is written; the value keeps its own below it.
            self.locs.add(child, key_node.start_mark)
            out[key] = self.build(value_node, child)
        for key, value in merged.items():
            out.setdefault(key, value)  # keys written in the mapping win over merged ones
        return out

    def _merge(self, node: yaml.Node, path: Path_, into: dict[str | int, Any]) -> None:
        """``<<: *defaults`` (or a list of them): the YAML merge key, as PyYAML's loader does.

        Merged values are located at the mapping that merges them, not at the anchor, so
        that the keys written beside ``<<`` keep their own positions.
        """
        locs, self.locs = self.locs, Locations(self.locs.file)
        try:
            value = self.build(node, path)
        finally:
            self.locs = locs
        for source in value if isinstance(value, list) else [value]:
            if not isinstance(source, dict):
                self.error(path, node.start_mark, "'<<' merges a mapping or a list of mappings")
                return
            for key, item in source.items():
                into.setdefault(key, item)  # the first source that has a key wins

    def _key(self, node: yaml.ScalarNode) -> str | int:
        """Integer keys (``0x123:``, a CAN id) are ints; every other key stays as written,
        so that ``yes:`` or ``null:`` name something rather than becoming True or None."""
        if node.tag.endswith(":int"):
            try:
                return int(self.loader.construct_object(node))
            except Exception:  # `!!int abc`: keep the text, the schema reports it
                pass
        return str(node.value)


def _written_values(text: str) -> int:
    """How many values the file writes, counted by libyaml's parser when PyYAML has it.

    About 20 times faster than composing the file in Python (a 256 KiB flow list of 130 000
    values: ~0.1 s instead of ~2.5 s), so an oversize file is refused before that cost. 0
    when libyaml is missing or the YAML is broken: the composer below counts (and reports)
    it then.
    """
    loader = getattr(yaml, "CSafeLoader", None)
    if loader is None:
        return 0
    node_events = (yaml.ScalarEvent, yaml.SequenceStartEvent, yaml.MappingStartEvent)
    count = 0
    try:
        for event in yaml.parse(text, Loader=loader):
            if isinstance(event, node_events):
                count += 1
                if count > MAX_WRITTEN_VALUES:
                    break
    except yaml.YAMLError:
        return 0
    return count


class _TooLarge(Exception):
    def __init__(self, aliased: bool) -> None:
        super().__init__()
        self.aliased = aliased


def parse_yaml(text: str, file: str = "<graph>") -> tuple[Any, Locations, list[Diagnostic]]:
    """Parse YAML into plain data plus locations; syntax errors become diagnostics."""
    locs = Locations(file)
    errors: list[Diagnostic] = []

    def fail(message: str, line: int = 1, col: int = 1) -> tuple[Any, Locations, list[Diagnostic]]:
        return None, locs, [Diagnostic(Severity.error, message, file=file, line=line, column=col)]

    if len(text) > MAX_FILE_BYTES:  # characters: at least as many bytes
        big = too_large(len(text.encode("utf-8", "replace")), file)
        return fail(big.message)
    if _written_values(text) > MAX_WRITTEN_VALUES:
        return fail(f"graph file too large: more than {MAX_WRITTEN_VALUES} values written")
    loader: _TagRecordingLoader | None = None
    try:
        loader = _TagRecordingLoader(text)
        root = loader.get_single_node()
        if root is None:
            return fail("empty graph file")
        data = _Constructor(locs, errors, loader.tagged).build(root, ())
    except yaml.MarkedYAMLError as e:
        mark = e.problem_mark or e.context_mark
        msg = f"YAML syntax: {e.problem or e.context}"
        if e.problem and e.context:
            msg += f" ({e.context}"
            if e.context_mark is not None and mark is not None and e.context_mark.line != mark.line:
                msg += f" on line {e.context_mark.line + 1}"
            msg += ")"
        return fail(msg, *((mark.line + 1, mark.column + 1) if mark else (1, 1)))
    except yaml.reader.ReaderError as e:
        # Raised before any mark exists: locate the offending character ourselves.
        pos = max(0, min(e.position, len(text)))
        line = text.count("\n", 0, pos) + 1
        col = pos - (text.rfind("\n", 0, pos) + 1) + 1
        char = e.character if isinstance(e.character, int) else ord(e.character[:1] or "\0")
        return fail(f"YAML syntax: control character U+{char:04X} is not allowed", line, col)
    except yaml.YAMLError as e:
        return fail(f"YAML syntax: {e}")
    except RecursionError:
        return fail("YAML nested too deeply")
    except _TooLarge as e:
        if e.aliased:
            return fail(
                f"graph file too large: its aliases expand to more than {MAX_YAML_NODES} values"
            )
        return fail(f"graph file too large: more than {MAX_WRITTEN_VALUES} values written")
    finally:
        if loader is not None:
            loader.dispose()
    return data, locs, errors


# --- pydantic errors -----------------------------------------------------------------------


def _members(tp: Any) -> list[tuple[Any, str | None]]:
    """The alternatives of a (possibly Optional/Annotated/union) type, with their Tag if any."""
    tag: str | None = None
    while typing.get_origin(tp) is typing.Annotated:
        tag = next((m.tag for m in tp.__metadata__ if isinstance(m, Tag)), tag)
        tp = tp.__origin__
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        return [m for arg in typing.get_args(tp) for m in _members(arg)]
    return [(tp, tag)]


def _field_names(model: type[BaseModel]) -> list[str]:
    return [f.alias or name for name, f in model.model_fields.items()]


def _walk(model: type[BaseModel], loc: tuple[Any, ...]) -> tuple[Path_, list[str]]:
    """Follow a pydantic error location through the model's types.

    Returns the location without the union tags pydantic inserts (``timer`` for the timer
    member of a trigger, ``str`` for the ``str`` member of ``str | list[str]``), and the
    field names valid beside the last element (for 'did you mean' on an unknown key).
    """
    path: list[str | int] = []
    here: list[tuple[Any, str | None]] = [(model, None)]
    siblings: list[str] = []
    for p in loc:
        tagged = [m for m in here if m[1] is not None and m[1] == p]
        if tagged:
            here = _members(tagged[0][0])
            continue
        siblings = [n for tp, _ in here if _is_model(tp) for n in _field_names(tp)]
        following: list[tuple[Any, str | None]] = []
        for tp, _ in here:
            origin, args = typing.get_origin(tp), typing.get_args(tp)
            if _is_model(tp):
                for name, f in tp.model_fields.items():
                    if p in (name, f.alias):
                        following += _members(f.annotation)
            elif origin is dict and len(args) == 2 and p != "[key]":
                following += _members(args[1])
            elif origin is list and args and isinstance(p, int):
                following += _members(args[0])
        if not following and isinstance(p, str) and len(here) > 1 and p not in siblings:
            continue  # the tag of a plain union member
        path.append(p)
        here = following
    return tuple(path), siblings


def _is_model(tp: Any) -> bool:
    return isinstance(tp, type) and issubclass(tp, BaseModel)


_TRIGGER_KEYS = ("frame", "timer", "input", "loop")


def pydantic_diagnostics(
    exc: ValidationError,
    locs: Locations,
    prefix: Path_ = (),
    model: type[BaseModel] = GraphSpec,
    only: Collection[str] | None = None,
) -> list[Diagnostic]:
    """Turn pydantic's errors into located diagnostics, with 'did you mean' for unknown keys.

    ``model`` is the model that was validated and ``prefix`` where its data sits in the file
    (a node's ``Params`` validated under ``("nodes", name, "params")``). ``only``: the
    top-level fields whose errors are wanted (a mode's params merged into a node's: the
    mode's own keys), None for all.
    """
    items: list[tuple[Path_, str]] = []
    suggested: set[Path_] = set()
    for err in exc.errors():
        if only is not None and (not err["loc"] or str(err["loc"][0]) not in only):
            continue
        rel, siblings = _walk(model, tuple(err["loc"]))
        path: Path_ = (*prefix, *rel)
        msg = err["msg"]
        if err["type"] == "extra_forbidden":
            key = str(path[-1])
            msg = f"unknown field {key!r}" + did_you_mean(key, siblings)
            if (match := closest(key, siblings)) is not None:
                suggested.add((*path[:-1], match))
        elif err["type"] == "missing" and path and isinstance(path[-1], int):
            # a tuple given too few items (``size: [320]``): said of the list, not of an
            # "item 1" the file never names
            path, msg = path[:-1], f"too few items: none at position {path[-1]} (from 0)"
        elif err["type"] == "missing":
            msg = f"missing required field {str(path[-1])!r}"
        elif err["type"] == "value_error":
            msg = str(err.get("ctx", {}).get("error", msg))
        elif err["type"] == "trigger" and isinstance(err["input"], dict | str):
            path, msg = _trigger_hint(path, err["input"], msg)
        if path and path[-1] == "[key]":
            path = path[:-1]
            msg = f"invalid name {str(path[-1])!r}: {msg}"
        items.append((path, msg))
    out: list[Diagnostic] = []
    merged: dict[Path_, int] = {}
    for path, msg in items:
        if msg.startswith("missing required field") and path in suggested:
            continue  # the misspelt key beside it already says "did you mean" this field
        if path in merged:  # several members of a union failed: one message
            d = out[merged[path]]
            out[merged[path]] = locs.diag(path, f"{d.message}, or {msg[0].lower()}{msg[1:]}")
            continue
        merged[path] = len(out)
        out.append(locs.diag(path, msg))
    return out


def _trigger_hint(path: Path_, given: dict[str, Any] | str, msg: str) -> tuple[Path_, str]:
    """Point a trigger without a known kind at its misspelt key."""
    if isinstance(given, str):
        return path, f"unknown trigger {given!r}" + did_you_mean(given, ("loop", "input"))
    for key in given:
        hint = did_you_mean(str(key), _TRIGGER_KEYS)
        if hint:
            return (*path, key), f"unknown trigger key {key!r}{hint}"
    return path, msg


# --- loading ---------------------------------------------------------------------------------


@dataclass
class Loaded:
    """A parsed graph file: the valid part of its spec, and every problem found so far.

    ``spec`` is None when nothing could be salvaged (bad YAML, no ``nodes`` mapping);
    otherwise it holds every node that passed validation, and ``invalid_nodes`` names the
    ones set aside, so that references to them are not reported as unknown.
    """

    spec: GraphSpec | None
    locs: Locations
    errors: list[Diagnostic]
    invalid_nodes: set[str] = field(default_factory=set)
    # an invalid node's kind and params, when those are well-formed: still checked, so that
    # a bad trigger does not hide a bad param of the same node (every problem at once)
    set_aside: dict[str, tuple[str, dict[str, Any]]] = field(default_factory=dict)


def check_text(text: str, file: str = "<graph>") -> Loaded:
    """Parse and validate a graph's text, collecting problems instead of raising."""
    data, locs, errors = parse_yaml(text, file)
    if data is None and errors:
        return Loaded(None, locs, errors)  # the YAML itself is broken
    return check_data(data, locs, errors)


def check_data(data: Any, locs: Locations, errors: Iterable[Diagnostic] = ()) -> Loaded:
    """Validate plain data as a graph, collecting problems instead of raising.

    ``errors`` are problems found before (while reading the YAML), reported with these.
    """
    errors = list(errors)
    if not isinstance(data, dict):
        errors.append(locs.diag((), "a graph file is a mapping with a 'nodes' key"))
        return Loaded(None, locs, errors)
    try:
        return Loaded(GraphSpec.model_validate(data), locs, errors)
    except ValidationError as e:
        errors = [*errors, *pydantic_diagnostics(e, locs)]
        salvaged = _without_invalid(data, e)
    if salvaged is None:
        return Loaded(None, locs, errors)
    kept, invalid = salvaged
    try:
        return Loaded(
            GraphSpec.model_validate(kept), locs, errors, invalid, _set_aside(data, invalid)
        )
    except ValidationError:
        return Loaded(None, locs, errors)


def _set_aside(data: dict[Any, Any], invalid: set[str]) -> dict[str, tuple[str, dict[str, Any]]]:
    """The kind and params of each node left out, where they are well-formed."""
    nodes = data.get("nodes")
    out: dict[str, tuple[str, dict[str, Any]]] = {}
    for name in invalid:
        node = nodes.get(name) if isinstance(nodes, dict) else None
        if not isinstance(node, dict):
            continue
        kind, params = node.get("kind"), node.get("params", {})
        if isinstance(kind, str) and isinstance(params, dict):
            out[name] = (kind, params)
    return out


# Node fields whose value shapes the graph: a node with a bad one is left out of the
# structural checks. A bad value of any other field (priority, deadline, an unknown key...)
# is only dropped, so the rest of its node is still checked.
_STRUCTURAL = ("kind", "params", "trigger", "inputs", "[key]")


def _without_invalid(
    data: dict[Any, Any], exc: ValidationError
) -> tuple[dict[Any, Any], set[str]] | None:
    """The graph minus what pydantic rejected, and the names of the nodes left out."""
    data = copy.deepcopy(data)
    nodes, modes = data.get("nodes"), data.get("modes")
    invalid: set[str] = set()
    dropped_modes: set[Any] = set()
    all_modes_dropped = False
    for err in exc.errors():
        loc = err["loc"]
        if not loc or (loc[0] == "nodes" and (len(loc) < 2 or not isinstance(nodes, dict))):
            return None
        if loc[0] == "nodes":
            assert isinstance(nodes, dict)
            node = nodes.get(loc[1])
            if len(loc) >= 3 and loc[2] not in _STRUCTURAL and isinstance(node, dict):
                node.pop(loc[2], None)
            elif loc[1] in nodes:
                del nodes[loc[1]]
                invalid.add(str(loc[1]))
        elif loc[0] == "modes" and len(loc) >= 2 and isinstance(modes, dict):
            mode = modes.get(loc[1])
            if len(loc) >= 4 and loc[2] == "nodes" and isinstance(mode, dict):
                mode_nodes = mode.get("nodes")
                if isinstance(mode_nodes, dict):
                    mode_nodes.pop(loc[3], None)
                    continue
            modes.pop(loc[1], None)
            dropped_modes.add(loc[1])
        else:
            data.pop(loc[0], None)
            all_modes_dropped = all_modes_dropped or loc[0] == "modes"
    # An invalid initial_mode was popped above, so what is left is a string or None.
    if all_modes_dropped or data.get("initial_mode") in dropped_modes:
        data.pop("initial_mode", None)  # not "unknown mode": its mode had errors of its own
    return data, invalid


def load_text(text: str, file: str = "<graph>") -> tuple[GraphSpec, Locations]:
    """Parse and validate a graph's text; raises GraphError listing every problem."""
    loaded = check_text(text, file)
    if loaded.spec is None or loaded.errors:
        raise GraphError(loaded.errors)
    return loaded.spec, loaded.locs


def read_graph_file(path: str | Path) -> str:
    """A graph file's text; a missing or unreadable file is a GraphError, not a traceback."""
    from ..files import NotARegularFile, read_text

    p = Path(path)
    try:
        size = p.stat().st_size
        if size > MAX_FILE_BYTES:  # refused before reading: no time or memory spent on it
            raise GraphError([too_large(size, str(p))])
        return read_text(p, MAX_FILE_BYTES)  # a device or a FIFO: refused, never read
    except NotARegularFile as e:
        raise GraphError(
            [Diagnostic(Severity.error, f"cannot read graph file: {e.strerror}", file=str(p))]
        ) from None
    except OSError as e:
        raise GraphError(
            [Diagnostic(Severity.error, f"cannot read graph file: {e.strerror}", file=str(p))]
        ) from None
    except UnicodeDecodeError:
        raise GraphError(
            [Diagnostic(Severity.error, "graph file is not UTF-8 text", file=str(p))]
        ) from None


def load_file(path: str | Path) -> tuple[GraphSpec, Locations]:
    """Read and validate a graph file; raises GraphError listing every problem."""
    return load_text(read_graph_file(path), str(path))
