"""``--cpu-latency``: a PM QoS CPU latency request held while the runtime runs.

(flowrt/system/_cpu_latency.py) The request holds while its file stays open; checked here:
what is written (a 32-bit bound in microseconds), every refusal said in words and never
fatal, the file closed at stop and after a failed start (the kernel drops the request then),
the bound in force while a run holds it (the real device, where this machine has one and we
may write it), the statistics and the table's title, the command line's range.
"""

from __future__ import annotations

import asyncio
import json
import os
import struct
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

import flowrt
from flowrt.system._cpu_latency import DEVICE, CpuLatencyRequest, current_bound_us


def _open_to(device: str) -> list[str]:
    """This process's file descriptors open on ``device``."""
    out = []
    for fd in os.listdir("/proc/self/fd"):
        try:
            if os.readlink(f"/proc/self/fd/{fd}") == device:
                out.append(fd)
        except OSError:
            continue
    return out


@pytest.mark.parametrize(
    ("seconds", "written"),
    [(0.0, 0), (20e-6, 20), (0.01, 10_000)],
)
def test_the_bound_is_written_in_microseconds_and_held_until_released(
    tmp_path: Path, seconds: float, written: int
) -> None:
    device = str(tmp_path / "cpu_dma_latency")
    Path(device).write_bytes(b"")
    req = CpuLatencyRequest(seconds, device)
    assert req.hold()
    assert req.granted == f"held at {written} us"
    assert struct.unpack("=i", Path(device).read_bytes()) == (written,)
    assert _open_to(device)  # the request is the open file
    req.release()
    assert not req.held
    assert _open_to(device) == []


@pytest.mark.parametrize(
    ("make", "said"),
    [
        (lambda p: p / "absent", "does not exist (no PM QoS here)"),
        (lambda p: p, "Is a directory"),  # any other refusal, in the system's words
    ],
)
def test_a_refusal_says_why_and_holds_nothing(tmp_path: Path, make: Any, said: str) -> None:
    req = CpuLatencyRequest(0.0, str(make(tmp_path)))
    assert not req.hold()
    assert req.granted.startswith("not held: ")
    assert said in req.granted
    assert not req.held


@pytest.mark.parametrize("seconds", [-1e-6, 0.0101, float("nan")])
def test_a_bound_out_of_range_is_refused_up_front(seconds: float) -> None:
    g = flowrt.GraphBuilder("g")
    with pytest.raises(ValueError, match="cpu_latency"):
        flowrt.Runtime(g.build(), cpu_latency=seconds)


class Tick(flowrt.Node):
    value = flowrt.Output(int)

    def process(self) -> int:
        return 1


class SlowSetup(flowrt.Node):
    value = flowrt.Output(int)

    async def setup(self) -> None:
        await asyncio.sleep(30)

    def process(self) -> int:
        return 1


def _writable_device() -> bool:
    try:
        os.close(os.open(DEVICE, os.O_WRONLY))
    except OSError:
        return False
    return True


needs_device = pytest.mark.skipif(
    not _writable_device(), reason=f"{DEVICE} is not writable here (root, PM QoS)"
)


@needs_device
async def test_a_run_holds_the_bound_and_its_stop_releases_it() -> None:
    g = flowrt.GraphBuilder("g")
    g.add("tick", Tick, trigger={"timer": "10ms"})
    rt = flowrt.Runtime(g.build(), cpu_latency=0.0)
    async with rt:
        await rt.run(0.05)
        assert current_bound_us() == 0  # every idle CPU may only poll now
        assert _open_to(DEVICE)
        assert rt.stats().cpu_latency == "held at 0 us"
    assert _open_to(DEVICE) == []  # closed: the kernel dropped the request


@needs_device
async def test_a_start_cut_short_releases_the_bound() -> None:
    """Ctrl-C during set-up (the start cancelled): what the start did is undone, this too."""
    g = flowrt.GraphBuilder("g")
    g.add("slow", SlowSetup, trigger={"timer": "10ms"})
    rt = flowrt.Runtime(g.build(), cpu_latency=0.0)
    start = asyncio.ensure_future(rt.start())
    await asyncio.sleep(0.2)
    assert _open_to(DEVICE)
    start.cancel()
    with pytest.raises(asyncio.CancelledError):
        await start
    assert _open_to(DEVICE) == []


@pytest.mark.parametrize(
    ("granted", "title"),
    [
        ("held at 0 us", "wake-up ≤ 0 us"),
        ("held at 10000 us", "wake-up ≤ 10 ms"),  # short at 80 columns, never cut to "≤ 10…"
        ("not held: /dev/cpu_dma_latency is not writable (needs root)", "wake-up bound not held"),
        ("", None),  # not asked for
    ],
)
def test_the_table_title_says_the_bound_or_that_it_is_not_held(
    granted: str, title: str | None
) -> None:
    from test_status_table import cambada_stats, show

    text = show(cambada_stats().model_copy(update={"cpu_latency": granted}), 80)[0]
    head = text.splitlines()[0]
    if title is None:
        assert "wake-up" not in head
    else:
        assert title in head


@pytest.mark.parametrize("wrong", ["0", True, [0.0]])
def test_a_bound_that_is_not_a_number_is_a_type_error(wrong: Any) -> None:
    with pytest.raises(TypeError, match="cpu_latency must be a number of seconds"):
        flowrt.Runtime(flowrt.GraphBuilder("g").build(), cpu_latency=wrong)


@pytest.mark.subprocess
def test_the_command_line_holds_it_and_says_so(tmp_path: Path) -> None:
    graph = Path(flowrt.__file__).parent / "examples" / "cambada.yaml"
    if not graph.exists():
        graph = Path(__file__).parents[1] / "graphs" / "cambada.yaml"
    out = tmp_path / "stats.json"
    cmd = [sys.executable, "-m", "flowrt.cli", "run", str(graph), "--no-ui", "--duration",
           "0.5", "--cpu-latency", "0us", "--stats-json", str(out)]  # fmt: skip
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    said = json.loads(out.read_text())["cpu_latency"]
    if _writable_device():
        assert said == "held at 0 us"
    else:
        assert said.startswith("not held: ")
        assert "--cpu-latency: not held" in r.stderr
    bad = subprocess.run([*cmd[:-4], "--cpu-latency", "11ms"], capture_output=True, text=True)
    assert bad.returncode == 2
    assert "--cpu-latency: must be between 0 and 10 ms, got 11 ms" in bad.stderr
    words = subprocess.run([*cmd[:-4], "--cpu-latency", "-1us"], capture_output=True, text=True)
    assert words.returncode == 2
    assert "expected a duration from 0 to 10 ms such as 0us or 300us, got '-1us'" in words.stderr
