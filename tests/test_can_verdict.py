"""``flowrt can analyse``'s verdict and ``flowrt can stats``'s load, as a user reads them
(issue 38 item 9, issue 43 item 7).

- never "schedulable" above 100 % utilisation; unknown (``null`` in ``--json``, a reason in
  the table) when nothing could be analysed, or when the load may or may not be over 100 %
  (an FD data phase at an unknown rate);
- a long "not analysed" list as a count and the first few (all of them in ``--json``);
- the bit/s figure in nominal bit times, the FD data phase at ``--data-bitrate``;
- errors carry the command's name; a short trace has no "busiest second".
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import can
import pytest
from _can_dbcs import FD_DBC, write

from flowrt import cli
from flowrt.analysis.can import CanMessageTiming, analyse_bus
from flowrt.analysis.can_frames import fd_frame_bits, frame_bits
from flowrt.cli.can import SHOWN

pytestmark = pytest.mark.timeout(30)


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    rc = cli.main(list(argv))
    got = capsys.readouterr()
    return rc, got.out, got.err


def _fd(i: int, period: float) -> CanMessageTiming:
    return CanMessageTiming(f"F{i}", 0x100 + i, 64, period, fd=True, brs=True)


def test_over_100_percent_with_nothing_analysed_is_unknown_not_yes() -> None:
    """The case seen: an FD DBC without a data bit rate, every message "not analysed", the
    no-BRS load 229 %: the verdict was yes. The data phase may be fast enough or not."""
    msgs = [_fd(i, 2.0) for i in range(4)]  # 4 x 712 bits / 2 ms at 500k: 285 % at no BRS
    result = analyse_bus(msgs, 500_000)
    assert result.utilisation > 1
    assert result.utilisation_min is not None
    assert result.utilisation_min < 1
    assert result.schedulable is None
    assert "nothing could be analysed" in result.verdict_reason
    doc = result.to_json()
    assert doc["schedulable"] is None
    assert doc["reason"] == result.verdict_reason


def test_over_100_percent_even_at_the_lower_bound_is_no() -> None:
    """Arbitration phases alone over the bus' time: no data rate can save it."""
    arb = fd_frame_bits(64, False, True).arbitration
    period = 0.9 * arb / 500  # each message's arbitration phase alone: 111 % of its period
    result = analyse_bus([_fd(0, period)], 500_000)
    assert result.utilisation_min == pytest.approx(arb / 500 / period)
    assert result.schedulable is False
    assert "over 100 %" in result.verdict_reason


def test_over_100_percent_classic_is_no_even_where_messages_pass() -> None:
    """The lowest-priority periodic message's busy period never ends, so it fails; with it
    event-driven the rest could pass, but the bus is over-full: no."""
    c = frame_bits(8) / 125  # 1.08 ms at 125 kbit/s
    msgs = [CanMessageTiming(f"M{i}", i, 8, 2 * c) for i in range(3)]
    result = analyse_bus(msgs, 125_000)
    assert result.utilisation == pytest.approx(1.5)
    assert result.schedulable is False


def test_nothing_with_a_cycle_time_is_unknown() -> None:
    result = analyse_bus([CanMessageTiming("E", 1, 8, None)], 500_000)
    assert result.schedulable is None
    assert "no message has a cycle time" in result.verdict_reason
    assert analyse_bus([], 500_000).schedulable is None


def test_a_schedulable_bus_has_no_reason() -> None:
    result = analyse_bus([CanMessageTiming("A", 1, 8, 10.0)], 500_000)
    assert result.schedulable is True
    assert result.verdict_reason == ""


def test_bits_per_s_honours_the_data_bitrate() -> None:
    """In nominal bit times: the 678-bit data phase of a 64-byte frame counts a quarter at
    2 Mbit/s over a 500 kbit/s nominal rate, an eighth at 4 Mbit/s."""
    fd = fd_frame_bits(64, False, True)
    msg = [_fd(0, 10.0)]
    at2 = analyse_bus(msg, 500_000, 2_000_000)
    at4 = analyse_bus(msg, 500_000, 4_000_000)
    assert at2.bits_per_s == pytest.approx(100 * (fd.arbitration + fd.data / 4))
    assert at4.bits_per_s == pytest.approx(100 * (fd.arbitration + fd.data / 8))
    for r in (at2, at4):
        assert r.bits_per_s == pytest.approx(r.utilisation * r.bitrate)
        assert r.arbitration_bits_per_s == pytest.approx(100 * fd.arbitration)
        assert r.data_bits_per_s == pytest.approx(100 * fd.data)


def _many_fd_dbc(n: int) -> str:
    """``n`` 64-byte FD messages with bit-rate switch every 20 ms, no data bit rate given."""
    head = FD_DBC.split("BO_ 256")[0]
    body = "".join(
        f'BO_ {0x100 + i} Msg{i}: 64 ECU\n SG_ S{i} : 0|8@1+ (1,0) [0|255] "" PC\n\n'
        for i in range(n)
    )
    attrs = "".join(
        f'BA_ "GenMsgCycleTime" BO_ {0x100 + i} 20;\nBA_ "VFrameFormat" BO_ {0x100 + i} 14;\n'
        for i in range(n)
    )
    tail = FD_DBC[FD_DBC.index("BA_DEF_ ") : FD_DBC.index('BA_ "BusType"')]
    return head + body + tail.replace('BA_DEF_DEF_  "BaudrateCANFD" 2000000;\n', "") + attrs


def test_cli_unknown_verdict_long_lists_shortened(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = write(tmp_path, _many_fd_dbc(60))
    rc, out, err = _run(capsys, "can", "analyse", path)
    assert rc == 1  # not shown schedulable
    assert err == ""
    verdict = next(line for line in out.splitlines() if line.startswith("bus:"))
    assert "schedulable: unknown (nothing could be analysed" in " ".join(out.split())
    assert "yes" not in verdict
    flat = " ".join(out.split())
    assert "60 messages: Msg0, Msg1, Msg2, Msg3, Msg4, ... (--json lists them all)" in flat
    assert f"Msg{SHOWN}," not in flat
    rc, out, _ = _run(capsys, "can", "analyse", path, "--json")
    assert rc == 1
    doc = json.loads(out)
    assert doc["schedulable"] is None
    assert doc["utilisation"] > 1
    assert doc["not_analysed_count"] == 60
    assert [m["name"] for m in doc["not_analysed"]] == [f"Msg{i}" for i in range(60)]
    rc, out, _ = _run(capsys, "can", "analyse", path, "--data-bitrate", "2M", "--json")
    doc = json.loads(out)
    assert doc["schedulable"] is False  # at 2 Mbit/s: 122 % of the bus
    assert doc["utilisation"] > 1
    assert "can miss their deadline" in doc["reason"]
    assert doc["bits_per_s"] == pytest.approx(doc["utilisation"] * 500_000)


@pytest.mark.parametrize(
    ("argv", "prefix"),
    [
        (["can", "analyse", "no/such.dbc"], "flowrt can analyse: "),
        (["can", "analyze", "no/such.dbc"], "flowrt can analyse: "),
        (["can", "analyse", "nodes/robot.dbc", "--bitrate", "3"], "flowrt can analyse: "),
        (["can", "stats", "no/such.blf"], "flowrt can stats: "),
    ],
)
def test_errors_name_the_command(
    capsys: pytest.CaptureFixture[str], argv: list[str], prefix: str
) -> None:
    rc, out, err = _run(capsys, *argv)
    assert rc == 2
    assert out == ""
    assert err.startswith(prefix)
    assert len(err.strip().splitlines()) == 1


def _trace(path: Path, seconds: float, start: float = 1000.2) -> str:
    with can.ASCWriter(str(path)) as w:
        for k in range(round(seconds / 0.01) + 1):
            w.on_message_received(
                can.Message(
                    timestamp=start + k * 0.01,
                    arbitration_id=0x10,
                    data=bytes(8),
                    is_extended_id=False,
                )
            )
    return str(path)


def test_stats_of_a_short_trace_say_no_busiest_second(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """1.5 s of a 10 ms frame: a "busiest second" of one whole second and half of one is no
    figure; the mean over the trace is."""
    path = _trace(tmp_path / "short.asc", 1.5)
    rc, out, _ = _run(capsys, "can", "stats", path)
    assert rc == 0
    assert not re.search(r"busiest second [0-9]", out)
    assert "over the whole trace (1.500 s: too short for a busiest second)" in " ".join(out.split())
    rc, out, _ = _run(capsys, "can", "stats", path, "--json")
    doc = json.loads(out)
    assert doc["peak_load"] is None
    assert doc["mean_load"] == pytest.approx(151 * 135 / 500_000 / 1.5, rel=1e-6)
    long = _trace(tmp_path / "long.asc", 3.0)
    rc, out, _ = _run(capsys, "can", "stats", long, "--json")
    doc = json.loads(out)
    assert doc["peak_load"] == pytest.approx(100 * 135 / 500_000)  # a whole second: 100 frames
    rc, out, _ = _run(capsys, "can", "stats", long)
    assert "busiest second 2.70 % (of 3.0 s)" in " ".join(out.split())


def test_the_can_example_graph_has_no_warning() -> None:
    """Issue 43: graphs/can.yaml warned about its own deadline (10 ms over a 5 ms tick)."""
    from flowrt.graph._resolve import Graph

    graph = Graph.from_file(Path(__file__).resolve().parent.parent / "graphs" / "can.yaml")
    assert graph.warnings == []
