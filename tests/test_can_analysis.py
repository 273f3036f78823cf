"""CAN bus analysis and the ``flowrt can`` commands, against published figures.

- Davis, Burns, Bril & Lukkien 2007, section 3 (table 2): three 7-data-byte messages at
  125 kbit/s (125 bits = 1 ms each), A every 2.5 ms, B and C every 3.5 ms with a 3.25 ms
  deadline. Tindell's original analysis gives C 3 ms (schedulable); the revised analysis,
  looking at the second instance of C in its busy period, gives 3.5 ms: a miss.
- The CAN paper on mobile robots: scenario 1 (piggybacked) 15 055 bit/s, scenario 2 (one
  1-byte message per sensor) 32 435 bit/s with the worst-case frame length.
"""

from __future__ import annotations

import json
from pathlib import Path

import can
import pytest

from flowrt import cli
from flowrt.analysis.can import CanMessageTiming, analyse_bus, frame_bits, response_time

pytestmark = pytest.mark.timeout(30)

BENCH = Path(__file__).resolve().parent.parent / "benchmarks" / "can"


@pytest.mark.parametrize(
    ("dlc", "extended", "bits"),
    [
        (0, False, 55),  # 47 + 0 + floor(33/4)
        (1, False, 65),
        (2, False, 75),
        (3, False, 85),
        (7, False, 125),  # the Davis et al. example: 1 ms at 125 kbit/s
        (8, False, 135),
        (0, True, 80),  # 67 + 0 + floor(53/4)
        (8, True, 160),
    ],
)
def test_frame_bits(dlc: int, extended: bool, bits: int) -> None:
    assert frame_bits(dlc, extended) == bits


def test_frame_bits_rejects_more_than_8_bytes() -> None:
    with pytest.raises(ValueError, match=r"0\.\.8"):
        frame_bits(9)


def _davis() -> list[CanMessageTiming]:
    return [
        CanMessageTiming("A", 1, 7, 2.5),
        CanMessageTiming("B", 2, 7, 3.5, deadline_ms=3.25),
        CanMessageTiming("C", 3, 7, 3.5, deadline_ms=3.25),
    ]


def test_davis_2007_example_revised_response_times() -> None:
    result = analyse_bus(_davis(), 125_000)
    by = {m.name: m for m in result.messages}
    assert [m.c_ms for m in result.messages] == pytest.approx([1.0, 1.0, 1.0])
    assert by["A"].wcrt_ms == pytest.approx(2.0)
    assert by["B"].wcrt_ms == pytest.approx(3.0)
    # the refutation: the second instance of C in the busy period takes 3.5 ms
    assert by["C"].wcrt_ms == pytest.approx(3.5)
    assert by["C"].busy_period_ms == pytest.approx(7.0)
    assert by["C"].instances == 2
    assert by["C"].blocking_ms == 0.0
    assert by["A"].blocking_ms == pytest.approx(1.0)
    assert by["C"].schedulable is False
    assert by["A"].schedulable
    assert by["B"].schedulable
    assert not result.schedulable
    assert result.utilisation == pytest.approx(1 / 2.5 + 2 / 3.5)


def test_first_instance_alone_is_the_flawed_answer() -> None:
    # Tindell's original analysis (only q = 0) gave 3 ms for C: check that our q = 0 term
    # is that figure, so the 3.5 ms above really comes from the later instance.
    c = 1.0
    higher = [(1.0, 2.5, 0.0), (1.0, 3.5, 0.0)]
    w = 0.0
    for _ in range(10):
        w = sum(-(-(w + j + 0.008) // t) * ck for ck, t, j in higher)
    assert w + c == pytest.approx(3.0)
    r, _, _ = response_time(c, 3.5, 0.0, 0.0, higher, 0.008)
    assert r == pytest.approx(3.5)


def test_jitter_adds_to_response_time() -> None:
    base = analyse_bus(_davis(), 125_000).messages[0].wcrt_ms
    jit = [CanMessageTiming("A", 1, 7, 2.5, jitter_ms=0.3), *_davis()[1:]]
    assert analyse_bus(jit, 125_000).messages[0].wcrt_ms == pytest.approx(base + 0.3)


def test_overloaded_bus_is_unbounded_not_a_hang() -> None:
    msgs = [CanMessageTiming(f"M{i}", i, 8, 1.0) for i in range(1, 4)]  # 3 x 1.08 ms / 1 ms
    result = analyse_bus(msgs, 125_000)
    assert result.utilisation > 1
    assert result.messages[-1].wcrt_ms is None
    assert result.messages[-1].schedulable is False


def test_extended_loses_to_standard_with_same_base_id() -> None:
    std = CanMessageTiming("S", 0x100, 8, 10.0)
    ext = CanMessageTiming("E", 0x100 << 18, 8, 10.0, extended=True)
    result = analyse_bus([ext, std], 500_000)
    assert [m.name for m in result.messages] == ["S", "E"]


@pytest.mark.parametrize(
    ("dbc", "bits_per_s"), [("scenario1.dbc", 15_055), ("scenario2.dbc", 32_435)]
)
def test_cli_reproduces_the_can_paper(
    dbc: str, bits_per_s: int, capsys: pytest.CaptureFixture[str]
) -> None:
    rc = cli.main(["can", "analyse", str(BENCH / dbc), "--bitrate", "125000", "--json"])
    doc = json.loads(capsys.readouterr().out)
    assert rc == 0
    assert round(doc["bitrate"] * doc["utilisation"]) == bits_per_s
    assert doc["schedulable"] is True
    for m in doc["messages"]:
        assert isinstance(m["id"], int)
        assert {
            "name",
            "id",
            "dlc",
            "period_ms",
            "frame_bits",
            "wcrt_ms",
            "deadline_ms",
            "schedulable",
        } <= set(m)
        assert isinstance(m["wcrt_ms"], float)
        assert m["wcrt_ms"] <= m["deadline_ms"]


DAVIS_DBC = """VERSION ""
NS_ :
BS_:
BU_: N
BO_ 1 A: 7 N
 SG_ a : 0|8@1+ (1,0) [0|255] "" N
BO_ 2 B: 7 N
 SG_ b : 0|8@1+ (1,0) [0|255] "" N
BO_ 3 C: 7 N
 SG_ c : 0|8@1+ (1,0) [0|255] "" N
BA_DEF_ BO_ "GenMsgCycleTime" FLOAT 0 100000;
BA_DEF_DEF_ "GenMsgCycleTime" 0;
BA_ "GenMsgCycleTime" BO_ 1 2.5;
BA_ "GenMsgCycleTime" BO_ 2 3.5;
BA_ "GenMsgCycleTime" BO_ 3 3.5;
"""


def test_cli_exit_1_when_not_schedulable(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "davis.dbc"
    path.write_text(DAVIS_DBC)
    args = ["can", "analyse", str(path), "--bitrate", "125000"]
    assert cli.main([*args, "--deadline", "B=3.25", "--deadline", "C=3.25"]) == 1
    out = capsys.readouterr().out
    assert "NO" in out
    assert "3.500" in out
    assert cli.main(args) == 0  # deadline = period 3.5 ms: just met


@pytest.mark.parametrize(
    ("text", "extra", "needle"),
    [
        ("BO_ 1 X: 9 Y\n garbage", [], "not a valid CAN database"),
        (DAVIS_DBC, ["--period", "Nope=10"], "not a message of the DBC"),
        (DAVIS_DBC, ["--jitter", "A"], "expected NAME=MS"),
    ],
)
def test_cli_bad_input_one_line_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str, extra: list[str], needle: str
) -> None:
    path = tmp_path / "x.dbc"
    path.write_text(text)
    assert cli.main(["can", "analyse", str(path), *extra]) == 2
    err = capsys.readouterr().err
    assert needle in err
    assert len(err.strip().splitlines()) == 1
    assert "Traceback" not in err


def test_stats_of_an_asc_trace(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    trace = tmp_path / "t.asc"
    with can.ASCWriter(str(trace)) as w:
        for k in range(100):  # 0x10 every 10 ms, 0x20 every 20 ms (jittered +-1 ms)
            w.on_message_received(
                can.Message(
                    timestamp=1000 + k * 0.010,
                    arbitration_id=0x10,
                    data=[1, 2, 3],
                    is_extended_id=False,
                )
            )
            if k % 2 == 0:
                jitter = 0.001 if k % 4 == 0 else -0.001
                w.on_message_received(
                    can.Message(
                        timestamp=1000 + k * 0.010 + 0.005 + jitter,
                        arbitration_id=0x20,
                        data=[1, 2],
                        is_extended_id=False,
                    )
                )
    path = tmp_path / "x.dbc"
    path.write_text((BENCH / "scenario1.dbc").read_text())
    rc = cli.main(["can", "stats", str(trace), "--dbc", str(path), "--bitrate", "125000", "--json"])
    doc = json.loads(capsys.readouterr().out)
    assert rc == 0
    assert doc["frames"] == 150
    ids = {r["id"]: r for r in doc["ids"]}
    assert ids[0x10]["count"] == 100
    assert ids[0x20]["count"] == 50
    assert ids[0x10]["name"] == "Encoders"
    assert ids[0x20]["name"] == "Infrared"
    assert ids[0x10]["period_ms"] == pytest.approx(10.0, abs=1e-3)
    assert ids[0x10]["std_ms"] == pytest.approx(0.0, abs=1e-3)
    assert ids[0x20]["period_ms"] == pytest.approx(20.0, abs=0.05)
    assert ids[0x20]["min_ms"] == pytest.approx(18.0, abs=1e-3)
    assert ids[0x20]["max_ms"] == pytest.approx(22.0, abs=1e-3)
    assert ids[0x20]["std_ms"] == pytest.approx(2.0, abs=1e-3)
    # 100 x 85 + 50 x 75 bits over 0.996 s
    assert doc["mean_load"] == pytest.approx((8500 + 3750) / doc["duration_s"] / 125000)


def test_stats_unreadable_trace_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "t.xyz"
    bad.write_text("hello")
    assert cli.main(["can", "stats", str(bad)]) == 2
    assert "cannot read the trace" in capsys.readouterr().err


@pytest.mark.parametrize("suffix", ["blf", "asc", "log", "csv", "trc"])
def test_stats_of_an_empty_trace_says_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], suffix: str
) -> None:
    """An empty .blf was "cannot read the trace: unpack requires a buffer of 72 bytes"."""
    empty = tmp_path / f"t.{suffix}"
    empty.write_bytes(b"")
    assert cli.main(["can", "stats", str(empty)]) == 2
    err = capsys.readouterr().err
    assert "an empty file (no CAN frame in it)" in err
    assert "unpack" not in err


@pytest.mark.parametrize("width", [80, 200])
def test_analyse_table_fits_the_terminal(monkeypatch: pytest.MonkeyPatch, width: int) -> None:
    import io

    from rich.console import Console

    import flowrt.cli.can as can_cli
    from flowrt.cli import main

    out = io.StringIO()
    monkeypatch.setattr(can_cli, "stdout_console", lambda: Console(width=width, file=out))
    assert main(["can", "analyse", "nodes/robot.dbc", "--bitrate", "250000"]) == 0
    lines = out.getvalue().splitlines()
    assert all(len(line) <= width for line in lines), lines
    table = "\n".join(lines)
    for name in ("MotorSetpoints", "WheelSpeeds", "Battery"):
        assert name in table  # names whole
    assert ("busy ms" in table) == (width > 100)  # derived terms go first at 80 columns
    assert "WCRT ms" in table
