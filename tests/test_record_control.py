"""What a running recorder is told (``flowrt ctl record``, the live view's record panel) and
what it says back (its state, its alerts).

- A start names its session with the name it gives, else the recorder's own ``name``: a name
  the page gave once (``named_001``) was kept, and a later ``flowrt ctl record start``
  recorded into ``named_002``.
- A writer that falls behind raises one ``HealthAlert`` when a burst of losses begins, not
  one per lost frame (``recorder behind: 1 lost`` ... ``15 lost`` flooded the event ring); every
  loss is still counted per stream.
"""

from __future__ import annotations

import asyncio
import os
import signal
from pathlib import Path
from typing import Any

import pytest
from conftest import wait_until

import flowrt
from flowrt import HealthAlert
from flowrt.cli.record import wait_for_writers
from flowrt.recording import RecordingReport
from flowrt.rtdb import RECORD_COMMAND, RECORDING_SESSION

pytestmark = pytest.mark.timeout(120)


def recording(rt: flowrt.Runtime) -> str:
    return str(rt.rtdb.value(RECORDING_SESSION + "rec", "") or "")


async def command(rt: flowrt.Runtime, value: Any, started: bool) -> str:
    """Write the recorder's command record (as ``ctl record`` and the page do) and wait for
    its answer; the session it says."""
    rt.rtdb.write(RECORD_COMMAND + "rec", value)
    assert await wait_until(lambda: (recording(rt) != "") == started)
    return recording(rt)


def counted(tmp_path: Path) -> flowrt.Graph:
    """A counter and a recorder that starts when told (``command``), into ``tmp_path``."""
    g = flowrt.GraphBuilder("counted")
    g.add("cnt", "counter", trigger={"timer": "20ms"})
    g.add(
        "rec",
        "recorder",
        params={"path": str(tmp_path), "start": False, "writer": "thread", "log_report": False},
        inputs={"cnt.value": {"from": "cnt.value", "policy": "lossless"}},
    )
    return g.build()


@pytest.mark.subprocess  # a recorder in the graph (its writer)
async def test_a_start_without_a_name_uses_the_recorders_own(tmp_path: Path) -> None:
    said = []
    async with flowrt.Runtime(counted(tmp_path)) as rt:
        said.append(await command(rt, {"action": "start", "name": "named"}, True))
        await command(rt, "stop", False)
        said.append(await command(rt, "start", True))  # flowrt ctl record start
        await command(rt, "stop", False)
        said.append(await command(rt, {"action": "start"}, True))  # a page's start, no name
        await command(rt, "stop", False)
    await asyncio.to_thread(wait_for_writers)
    assert [Path(s).name for s in said] == ["named_001", "rec_001", "rec_002"]


def _frames_graph(tmp: Path) -> flowrt.Graph:
    g = flowrt.GraphBuilder("behind")
    g.add("cam", "capture", params={"source": "synthetic:soccer", "fps": 50, "size": [80, 60]})
    g.add(
        "rec",
        "recorder",
        params={"path": str(tmp), "name": "drive", "max_frames": 1, "log_report": False},
        inputs={"cam.frame": {"from": "cam.frame", "policy": "lossless"}},
    )
    return g.build()


@pytest.mark.subprocess  # the recorder's writer process
async def test_a_writer_behind_raises_one_alert_per_burst_and_counts_every_loss(
    tmp_path: Path,
) -> None:
    async with flowrt.Runtime(_frames_graph(tmp_path)) as rt:
        assert await wait_until(lambda: recording(rt) != "")
        rec: Any = rt.scheduler.runners["rec"].executor.node  # type: ignore[attr-defined]
        assert await wait_until(lambda: getattr(rec.writer, "pid", None) is not None)
        pid = rec.writer.pid
        streams = rec.writer.streams

        def lost() -> int:
            return sum(s.lost_behind for s in streams.values())

        os.kill(pid, signal.SIGSTOP)  # the disk (or the writer) stalls
        try:
            assert await wait_until(lambda: lost() >= 10, within=20)
        finally:
            os.kill(pid, signal.SIGCONT)
        await rt.run(0.2)
        alerts = [
            e
            for e in rt.events
            if isinstance(e, HealthAlert) and e.node == "rec" and "recorder behind" in e.detail
        ]
        state = rt.stats().node("rec")
    await asyncio.to_thread(wait_for_writers)
    assert len(alerts) == 1, [a.detail for a in alerts]
    assert state.state == "error"  # red until the next session
    assert the_report(tmp_path).lost >= 10  # every loss counted, after the alert as before


def the_report(tmp: Path) -> RecordingReport:
    (session,) = sorted(tmp.glob("drive_*"))
    return RecordingReport.model_validate_json((session / "streams.json").read_text())


class _Ctx:
    """What :class:`LossAlerts` uses of a node's context: the clock and the error state."""

    name = "rec"

    def __init__(self) -> None:
        self.t = 0.0
        self.reasons: list[str] = []

    def now(self) -> float:
        return self.t

    def set_error(self, reason: str) -> None:  # an alert per new reason (NodeContext)
        if not self.reasons or self.reasons[-1] != reason:
            self.reasons.append(reason)


class _Stream:
    def __init__(self, topic: str) -> None:
        self.topic, self.lost_behind = topic, 0


class _Writer:
    error = None

    def __init__(self) -> None:
        self.streams = {"cam.frame": _Stream("cam.frame")}


def test_a_burst_ends_after_a_quiet_second_and_the_next_one_is_said_again() -> None:
    from flowrt.nodes.recorder import BURST_QUIET, LossAlerts

    ctx, alerts = _Ctx(), LossAlerts()
    writer: Any = _Writer()  # the counters a writer keeps per stream
    s = writer.streams["cam.frame"]
    for i in range(15):  # one loss every 50 ms, values accepted between them: one burst
        ctx.t = i * 0.05
        s.lost_behind += 1
        alerts.watch(ctx, writer)
        ctx.t += 0.025
        alerts.watch(ctx, writer)
    assert len(ctx.reasons) == 1
    assert ctx.reasons[0].startswith("recorder behind: 1 lost (cam.frame: 1)")
    ctx.t += BURST_QUIET + 0.1  # quiet: the burst is over
    alerts.watch(ctx, writer)
    s.lost_behind += 1
    alerts.watch(ctx, writer)
    assert len(ctx.reasons) == 2
    assert ctx.reasons[1].startswith("recorder behind: 16 lost (cam.frame: 16)")


@pytest.mark.subprocess  # a recorder in the graph (its writer)
async def test_the_end_reports_every_session_of_a_stop_and_start(tmp_path: Path) -> None:
    """``flowrt ctl record stop`` then ``start``: the end's table and ``--json`` said only
    the first session (the second's figures were in ``--stats-json`` alone)."""
    from rich.console import Console

    from flowrt.cli.record import _report_all, _sessions

    said = []
    async with flowrt.Runtime(counted(tmp_path)) as rt:
        for _ in range(2):
            said.append(await command(rt, "start", True))
            await asyncio.sleep(0.2)
            await command(rt, "stop", False)
    await asyncio.to_thread(wait_for_writers)
    first = Path(said[0])
    sessions = _sessions(rt, "rec", first)
    assert sessions == [Path(s) for s in said]
    console = Console(record=True, width=100)
    result: dict[str, Any] = {}
    assert _report_all(console, console, sessions, result) == 0
    shown = console.export_text()
    assert "recording rec_001" in shown
    assert "recording rec_002" in shown
    assert result["recording"]["session"] == "rec_001"
    assert [r["session"] for r in result["recordings"]] == ["rec_001", "rec_002"]
    assert all(r["streams"][0]["written"] > 0 for r in result["recordings"])
