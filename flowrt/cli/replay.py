"""``flowrt replay PATH``: the recorded streams stand in for the graph's sources of the same
names (``--graph``), or replay nodes publish them alone.

Also where a path on the command line becomes its MCAP files (:func:`_files`), which
``flowrt info`` shares.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from pathlib import Path
from typing import Any

from rich.console import Console

from ..recording.session import not_a_recording, sessions_hint
from .common import (
    EXIT_BAD_GRAPH,
    EXIT_FAILED,
    load,
    printable,
    safe_node_names,
    stdout_console,
)
from .recorders import RECORDER, select_outputs, split_patterns
from .run import run_graph


def _files(path: str, err: Console, cmd: str) -> list[Path] | None:
    from ..recording.session import mcap_files

    p = Path(path)
    if not p.exists():
        err.print(f"flowrt {cmd}: {path}: no such file or folder", markup=False)
        return None
    try:
        files = mcap_files(p)
    except ValueError as e:  # a rosbag2 folder flowrt cannot read (compressed): why
        err.print(f"flowrt {cmd}: {e}", markup=False)
        return None
    if not files:
        err.print(
            f"flowrt {cmd}: {path}: no .mcap file in this folder{sessions_hint(p, printable)}",
            markup=False,
        )
        return None
    return files


def cmd_replay(args: argparse.Namespace) -> int:
    from ..graph._resolve import resolve

    if args.deterministic:
        from .deterministic import cmd_replay_deterministic

        return cmd_replay_deterministic(args)
    err = Console(stderr=True, highlight=False, soft_wrap=True)
    console = stdout_console()
    checked = _recording(args, err)
    if checked is None:
        return EXIT_BAD_GRAPH
    files, path, info = checked
    streams = _chosen_streams(info, args.topics, err)
    if streams is None:
        return EXIT_BAD_GRAPH
    left_out = _left_out(files, streams, err)
    streams = [s for s in streams if s.topic not in left_out]
    if not streams:
        err.print(f"flowrt replay: {path}: nothing to replay (no stream decodes)", markup=False)
        return EXIT_BAD_GRAPH
    by_node: dict[str, list[str]] = {}
    for s in streams:
        by_node.setdefault((s.source or s.topic).split(".")[0], []).append(s.topic)

    # absolute: a path on the command line is relative to the working directory, never to
    # the graph file (the replay node resolves relative params against the graph's folder)
    common = {
        "path": str(path.resolve()),
        "rate": args.rate,
        "start": args.start,
        "loop": args.loop,
    }
    graph = _replay_target(args, info, path, err)
    if graph is _REFUSED:
        return EXIT_BAD_GRAPH
    built = _replay_spec(args, info, graph, by_node, common, err)
    if built is None:
        return EXIT_BAD_GRAPH
    spec, kinds, into = built
    try:
        base = Path(args.graph).resolve().parent if args.graph else None
        rgraph = resolve(spec, kinds=kinds, base_dir=base)
    except Exception as e:
        err.print(f"flowrt replay: {e}", markup=False)
        return EXIT_BAD_GRAPH
    parts = f", {len(files)} files" if len(files) > 1 else ""
    console.print(
        f"replaying {printable(str(path))} ({len(streams)} stream(s), "
        f"{info.duration:.1f} s{parts}) at x{args.rate:g} into {printable(into)}",
        highlight=False,
        markup=False,
    )
    result = {"path": str(path), "streams": [s.topic for s in streams], "into": into}
    code = run_graph(rgraph, args, err, prog="flowrt replay", kinds=kinds, result=result)
    if not info.closed_cleanly or left_out:  # not everything asked for was replayed
        return max(code, EXIT_FAILED)
    return code


def _recording(args: argparse.Namespace, err: Console) -> tuple[list[Path], Path, Any] | None:
    """The recording's files, its path and what a scan found, once the options and the files
    are fit to replay (None: refused, said why in one line)."""
    from ..recording.reader import scan_session

    if args.inline:
        err.print("flowrt replay: --inline goes with --deterministic", markup=False)
        return None
    if args.rate <= 0:
        err.print("flowrt replay: --rate must be positive", markup=False)
        return None
    files = _files(args.path, err, "replay")
    if files is None:
        return None
    for f in files:
        if (why := not_a_recording(f)) is not None:
            err.print(f"flowrt replay: {f}: {why}", markup=False)
            return None
    path = Path(args.path)
    info = scan_session(path)
    if not info.messages:
        why = info.damage or "no messages"
        err.print(f"flowrt replay: {path}: nothing to replay ({why})", markup=False)
        return None
    if not info.closed_cleanly:
        _say_damage(info, path, err)
    if args.start >= info.duration and info.duration > 0:
        err.print(
            f"flowrt replay: --start {args.start:g}s is past the end ({info.duration:.1f} s)",
            markup=False,
        )
        return None
    return files, path, info


def _replay_spec(
    args: argparse.Namespace,
    info: Any,
    graph: Any,
    by_node: dict[str, list[str]],
    common: dict[str, Any],
    err: Console,
) -> tuple[Any, dict[str, Any], str] | None:  # the spec, the kinds it adds, what it replays into
    """``--graph``'s graph with replay nodes for its sources, or replay nodes alone (None: no)."""
    from ..graph._registry import resolve_kind
    from ..graph.spec import GraphSpec, NodeSpec

    kinds: dict[str, Any] = {}
    replay_cls: Any = resolve_kind("replay")
    if graph is not None:
        graph_name = args.graph or "the recorded graph"
        nodes = dict(graph.spec.nodes)
        for name, nspec in graph.spec.nodes.items():
            if nspec.kind == RECORDER or nspec.inputs or name not in by_node:
                continue
            kind = f"replay-as-{name}"
            kinds[kind] = replay_cls.standing_in_for(graph.nodes[name].cls, name)
            nodes[name] = NodeSpec(
                kind=kind,
                params={**common, "node": name, "topics": by_node[name]},
                priority=nspec.priority,
            )
        if not kinds:
            err.print(
                f"flowrt replay: no source node of {graph_name} has recorded streams "
                f"(recorded from: {', '.join(by_node)})",
                markup=False,
            )
            return None
        spec: Any = graph.spec.model_copy(update={"nodes": nodes})
        replaced = sorted(k.removeprefix("replay-as-") for k in kinds)
        into = f"{graph_name}, replacing its source node(s) {', '.join(replaced)}"
    else:
        # Only the recorded streams: node names and topics from the file are plain strings
        # here; nothing the recording names is imported (but flowrt's own built-in kinds,
        # :func:`_builtin_types`), served or sent to. Each node publishes on the ports its
        # streams were recorded from, so a live view serves the recording's topics.
        _builtin_types(info.streams)
        nodes = {}
        for name, node in safe_node_names(by_node).items():
            params = {**common, "topics": by_node[name]}
            ports = _recorded_ports(name, [s for s in info.streams if s.topic in by_node[name]])
            own = replay_cls.with_ports(ports, node) if ports else None
            if own is not None:
                kinds[f"replay-of-{node}"] = own
                params["node"] = name
            nodes[node] = NodeSpec(kind=f"replay-of-{node}" if own else "replay", params=params)
        spec = GraphSpec(name="replay", nodes=nodes)
        into = "replay nodes publishing the recorded streams"
        if info.graph:
            err.print(
                "flowrt replay: the recording holds a graph; it is not run (a recording is "
                "data): give --graph FILE, or --trust-graph to run the recorded one",
                markup=False,
            )
    return spec, kinds, into


def _recorded_ports(node: str, streams: list[Any]) -> dict[str, Any] | None:
    """port -> type of the outputs ``node``'s streams were recorded from (their ``source``,
    ``node.port``): frames for images, audio blocks, anything else. None when a stream has
    no such source (another writer's topics): the generic ``frame``/``message`` ports then.
    A sync set's members (``node.port/KEY``) are joined into their set's port."""
    from ..audio import AudioBlock
    from ..frames import Frame
    from ..recording.encoding import AUDIO_SCHEMA
    from ..recording.images import is_image_schema

    ports: dict[str, Any] = {}
    members: set[str] = set()
    for s in streams:
        owner, dot, port = (s.source or "").partition(".")
        if owner != node or not dot:
            return None
        if "/" in port:
            members.add(port.partition("/")[0])
            continue
        audio = s.schema_name in (AUDIO_SCHEMA, "flowrt_msgs/msg/AudioBlock")
        ports[port] = Frame if is_image_schema(s.schema_name) else AudioBlock if audio else object
    return ports if members <= set(ports) else None


def _builtin_types(streams: list[Any]) -> None:
    """Import the modules of flowrt's built-in kinds whose dataclasses the streams were
    recorded as (JSON schema ``flowrt.nodes.can.values.CanMessage``), so that a replay
    gives the dataclass back, and a live view serves the recorded schema, not one guessed
    from a dict. Only modules of the ``flowrt.nodes`` package (shipped with flowrt, imported
    by any graph naming a built-in kind), never another module a file names."""
    from importlib import import_module

    for s in streams:
        module = s.schema_name.rpartition(".")[0]
        if s.message_encoding != "json" or not module.startswith(_BUILTIN_PACKAGE):
            continue
        if module in sys.modules or not all(
            part.isidentifier() and not part.startswith("_") for part in module.split(".")
        ):
            continue
        with contextlib.suppress(Exception):  # not there, or its dependency missing: the
            import_module(module)  # values stay mappings


_BUILTIN_PACKAGE = "flowrt.nodes."


_REFUSED: Any = object()


def _say_damage(info: Any, path: Path, err: Console) -> None:
    """A session not closed cleanly replays up to its first damage, whichever file; one
    that lacks a part replays the parts it has (exit 1: not everything was replayed)."""
    if info.missing:
        err.print(
            f"flowrt replay: {path}: {info.damage}: replaying the {info.messages} messages "
            "of the parts it has",
            markup=False,
        )
        return
    before = 0
    for part in info.files:
        before += part.messages
        if not part.closed_cleanly:
            break
    err.print(
        f"flowrt replay: {path} was not closed cleanly ({info.damage}): "
        f"replaying the {before} messages before the damage",
        markup=False,
    )


def _left_out(files: list[Path], streams: list[Any], err: Console) -> dict[str, str]:
    """The chosen streams no decoder reads, one line each on ``err``: left out of the replay."""
    from ..recording.decoding import undecodable

    left = undecodable(files, [s.topic for s in streams])
    for topic, why in left.items():
        err.print(
            f"flowrt replay: {printable(topic)}: left out, cannot decode ({why})", markup=False
        )
    return left


def _chosen_streams(info: Any, topics: Any, err: Console) -> list[Any] | None:
    """The recorded streams to replay (``--topics``); None: refused, said on ``err``."""
    from ..recording.encoding import ANNOTATIONS_SCHEMA

    # annotations are drawn from the detections, which are replayed themselves
    streams = [s for s in info.streams if s.schema_name != ANNOTATIONS_SCHEMA]
    patterns = split_patterns(topics)
    if not patterns:
        return streams
    names = [s.topic for s in streams]
    chosen, unmatched = select_outputs(names, patterns)
    # a ros2 recording's topics are ROS names (/pair/set), its sources flowrt's (pair.set)
    sources = [s.source for s in streams if s.source and s.source != s.topic]
    by_source, unmatched_too = select_outputs(sources, patterns) if sources else ([], unmatched)
    unmatched = [p for p in unmatched if p in unmatched_too]
    if unmatched:
        err.print(
            f"flowrt replay: --topics {', '.join(map(repr, unmatched))} matches no "
            f"recorded stream ({', '.join(names)})",
            markup=False,
        )
        return None
    return [s for s in streams if s.topic in chosen or (s.source and s.source in by_source)]


def _replay_target(args: argparse.Namespace, info: Any, path: Path, err: Console) -> Any:
    """The graph a replay runs: ``--graph``, the recorded one with ``--trust-graph``, or None
    (the recorded streams alone). ``_REFUSED`` after one line on ``err``."""
    from ..graph._resolve import Graph

    if args.graph:
        graph = load(args.graph, err)
        return _REFUSED if graph is None else graph
    if not args.trust_graph:
        return None
    if not info.graph:
        err.print(f"flowrt replay: {path}: --trust-graph: no graph is recorded", markup=False)
        return _REFUSED
    try:
        return Graph.from_text(info.graph, f"{path} (recorded graph)")
    except Exception as e:  # a malformed stored graph: one line
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        err.print(
            f"flowrt replay: the recorded graph is not valid: {printable(first)}", markup=False
        )
        return _REFUSED
