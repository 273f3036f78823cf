"""A recorder swapped while it records (``flowrt ctl swap rec recorder --params ...``) loses
nothing: the session goes on as a new one (``drive_001`` then ``drive_002``: the new params,
a new file), each value of a lossless edge is in one of the two, and the statistics'
``reports`` keep both sessions' tables (the new instance's had only its own).

The new instance obeyed the standing ``start`` at its first activation, after it had taken
over, and the values it took while its writer opened were in neither file: 2-4 of a 20 Hz
counter per swap, with both ``streams.json`` saying ``lost 0`` and the edge ``dropped 0``.
"""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import pytest
from conftest import wait_until
from mcap.reader import make_reader

import flowrt
from flowrt.cli.record import wait_for_writers
from flowrt.recording import RecordingReport
from flowrt.rtdb import RECORD_COMMAND, RECORDING_SESSION

pytestmark = pytest.mark.timeout(120)


def counter_graph(tmp: Path, writer: str) -> flowrt.Graph:
    g = flowrt.GraphBuilder("swap")
    g.add("cnt", "counter", trigger={"timer": "10ms"})
    g.add(
        "rec",
        "recorder",
        params={"path": str(tmp), "start": False, "log_report": False, "writer": writer},
        inputs={"cnt.value": {"from": "cnt.value", "policy": "lossless"}},
    )
    return g.build()


def counts(session: Path) -> list[int]:
    with (session / f"{session.name}.mcap").open("rb") as f:
        return [
            json.loads(m.data)["value"]
            for _, _, m in make_reader(f).iter_messages(topics=["cnt.value"])
        ]


def sessions(tmp: Path, prefix: str) -> list[Path]:
    return sorted(tmp.glob(f"{prefix}_*"))


def recording(rt: flowrt.Runtime) -> str:
    return str(rt.rtdb.value(RECORDING_SESSION + "rec", "") or "")


@pytest.mark.subprocess  # the recorder's writer process
@pytest.mark.parametrize("writer", ["process", "thread"])
async def test_a_swap_while_recording_loses_no_value(tmp_path: Path, writer: str) -> None:
    async with flowrt.Runtime(counter_graph(tmp_path, writer)) as rt:
        rt.rtdb.write(RECORD_COMMAND + "rec", {"action": "start", "name": "drive"})
        assert await wait_until(lambda: recording(rt) != "")
        await rt.run(0.3)
        first = recording(rt)
        await rt.swap("rec", "recorder", {"compression": "zstd"})
        said = recording(rt)
        await rt.run(0.3)
        rt.rtdb.write(RECORD_COMMAND + "rec", "stop")
        assert await wait_until(lambda: recording(rt) == "")
        await wait_until(lambda: len(rt.stats().reports.get("rec") or []) >= 2)
        reported = [r["session"] for r in rt.stats().reports.get("rec") or []]
        edge = next(e for e in rt.stats().edges if e.name.startswith("cnt.value->rec"))
    await asyncio.to_thread(wait_for_writers)
    assert edge.dropped == 0
    made = sessions(tmp_path, "drive")
    assert [s.name for s in made] == ["drive_001", "drive_002"]
    old, new = counts(made[0]), counts(made[1])
    assert old
    assert new
    assert old == list(range(old[0], old[-1] + 1))
    assert new == list(range(new[0], new[-1] + 1))
    assert new[0] == old[-1] + 1  # the new instance's first value follows the old one's last
    for s in made:
        report = RecordingReport.model_validate_json((s / "streams.json").read_text())
        assert report.lost == 0
        assert [x.received for x in report.streams] == [len(counts(s))]
    assert said == str(made[1])  # at the take-over: never "stopped" in between
    assert first == str(made[0])
    assert reported == ["drive_001", "drive_002"]  # the statistics keep both tables


@pytest.mark.subprocess  # the recorder's writer process
async def test_a_swap_of_a_stopped_recorder_starts_nothing(tmp_path: Path) -> None:
    """The standing command is obeyed by the new instance as it was by the old: ``stop``
    even though the graph says ``start: true`` (it made a session and closed it at once)."""
    g = counter_graph(tmp_path, "thread")
    async with flowrt.Runtime(g) as rt:
        rt.rtdb.write(RECORD_COMMAND + "rec", "start")
        assert await wait_until(lambda: recording(rt) != "")
        await rt.run(0.2)
        rt.rtdb.write(RECORD_COMMAND + "rec", "stop")
        assert await wait_until(lambda: recording(rt) == "")
        await rt.swap("rec", "recorder", {"start": True, "compression": "lz4"})
        await rt.run(0.3)
        assert recording(rt) == ""
    await asyncio.to_thread(wait_for_writers)
    assert [s.name for s in sessions(tmp_path, "rec")] == ["rec_001"]
