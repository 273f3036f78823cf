"""The ``/flowrt/stats`` channel's schema types the values of its mappings (D8).

``reports``, ``nodes[].output_hz``, ``edges[].drop_reasons`` and ``worker_frames[].by_socket``
are keyed by names known only at run time (nodes, ports, reasons), so their schema cannot
list ``properties``; they were ``{"type": "object", "properties": {}}``, which says nothing
of the counters and reports they carry. Their values' schema is now ``additionalProperties``:
a validator checks every value, and the apps' parser, which reads ``properties`` only, still
reads the topic. Checked on a real run's statistics, written as the live server writes them.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import jsonschema

from flowrt import Graph, Runtime, VirtualClock
from flowrt.graph._resolve import resolve
from flowrt.recording.encoding import encode_json
from flowrt.recording.jsonschema import schema_problems
from flowrt.recording.live import _json_schema
from flowrt.stats import RuntimeStats, WorkerFrameStats

REPO = Path(__file__).resolve().parents[1]


def stats_schema() -> dict[str, Any]:
    return dict(json.loads(_json_schema("flowrt.RuntimeStats").data))


async def agent_stats() -> RuntimeStats:
    """A run's statistics: the agent graph's arbiter reports nested objects, lists, booleans."""
    spec = Graph.from_file(REPO / "graphs" / "agent.yaml").spec
    nodes = {k: v for k, v in spec.nodes.items() if v.kind != "display"}
    clock = VirtualClock()
    async with Runtime(resolve(spec.model_copy(update={"nodes": nodes})), clock=clock) as rt:
        await clock.advance(1.0)
        return rt.stats()


def test_every_mapping_of_the_stats_has_a_schema_for_its_values() -> None:
    props = stats_schema()["properties"]
    maps = {
        "reports": props["reports"],
        "output_hz": props["nodes"]["items"]["properties"]["output_hz"],
        "drop_reasons": props["edges"]["items"]["properties"]["drop_reasons"],
        "by_socket": props["worker_frames"]["items"]["properties"]["by_socket"],
    }
    values = {name: m.get("additionalProperties") for name, m in maps.items()}
    assert values == {
        # a report is any JSON value but null: a recorder's is a list, most are objects
        "reports": {"not": {"type": "null"}},
        "output_hz": {"type": "number"},  # a None (on events) is left out, never null
        "drop_reasons": {"type": "integer"},
        "by_socket": {"type": "integer"},
    }
    assert all(m["type"] == "object" and m["properties"] == {} for m in maps.values())
    assert schema_problems(stats_schema()) == []  # still read by the apps' parser


async def test_a_runs_stats_as_the_live_server_writes_them_validate() -> None:
    stats = await agent_stats()
    assert isinstance(stats.reports["drive"]["sources"], dict)  # a real, nested report
    # what the run did not make: a recorder's report (a list), a rate per output, drops and
    # socket frames by reason (counted at stop, or by worker nodes)
    node = stats.nodes[0].model_copy(update={"output_hz": {"output": 20.0, "events": None}})
    edge = stats.edges[0].model_copy(update={"drop_reasons": {"queue full": 3, "stop": 1}})
    stats = stats.model_copy(
        update={
            "reports": {**stats.reports, "rec": [{"session": "run_001", "error": None}]},
            "nodes": [node, *stats.nodes[1:]],
            "edges": [edge, *stats.edges[1:]],
            "worker_frames": [
                WorkerFrameStats(
                    node="cam",
                    in_slots=9,
                    by_socket={"no-free-slot": 2},
                    granted=4,
                    outstanding=1,
                    refused=0,
                    reclaimed=0,
                )
            ],
        }
    )
    stream = _json_schema("flowrt.RuntimeStats")
    message = json.loads(encode_json(stats, stream).data)
    validator = jsonschema.Draft202012Validator(stats_schema())
    assert [e.message for e in validator.iter_errors(message)] == []
    assert message["nodes"][0]["output_hz"] == {"output": 20.0}
    assert message["reports"]["rec"] == [{"session": "run_001", "error": None}]

    # the values are typed: a counter that is not a number no longer passes
    wrong = json.loads(json.dumps(message))
    wrong["edges"][0]["drop_reasons"]["queue full"] = "3"
    wrong["nodes"][0]["output_hz"]["output"] = "fast"
    wrong["worker_frames"][0]["by_socket"]["no-free-slot"] = {"n": 2}
    wrong["reports"]["rec"] = None
    paths = sorted(".".join(map(str, e.absolute_path)) for e in validator.iter_errors(wrong))
    assert paths == [
        "edges.0.drop_reasons.queue full",
        "nodes.0.output_hz.output",
        "reports.rec",
        "worker_frames.0.by_socket.no-free-slot",
    ]


async def test_the_live_message_validates_against_flowrt_schema_stats_too() -> None:
    """One set of statistics, two readers' schemas: a script that validates what it reads
    live (or from a recording's ``/flowrt/stats``) with ``flowrt schema stats`` (the
    ``--stats-json`` schema). A value the live writer leaves out (None) must not be one that
    schema requires: a node without a deadline, one never run (no start, no finish)."""
    stats = await agent_stats()
    never = stats.nodes[0].model_copy(
        update={"deadline_ms": None, "last_start": None, "last_finish": None}
    )
    stats = stats.model_copy(update={"nodes": [never, *stats.nodes[1:]]})
    message = json.loads(encode_json(stats, _json_schema("flowrt.RuntimeStats")).data)
    assert "last_start" not in message["nodes"][0]  # left out, as the live server writes it
    cli = jsonschema.Draft202012Validator(RuntimeStats.model_json_schema(by_alias=True))
    assert [f"{list(e.absolute_path)}: {e.message}" for e in cli.iter_errors(message)] == []
    dumped = stats.model_dump(mode="json")  # what --stats-json writes: nulls kept
    assert dumped["nodes"][0]["last_start"] is None
    assert list(cli.iter_errors(dumped)) == []
