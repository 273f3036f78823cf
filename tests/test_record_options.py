"""``flowrt record`` is a run: it takes every option of ``flowrt run``, fails the same way."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest

from tests.test_record import GRAPH, flowrt_cli

pytestmark = pytest.mark.timeout(90)


@pytest.fixture
def graph_file(tmp_path: Path) -> Path:
    p = tmp_path / "g.yaml"
    p.write_text(GRAPH)
    return p


def test_record_takes_the_run_options(graph_file: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    stats = tmp_path / "stats.json"
    r = flowrt_cli(
        "record", str(graph_file), "-o", str(out), "--no-ui", "--duration", "1s",
        "--drain-timeout", "2", "--keep-going", "--spin", "100us", "--stats-json", str(stats),
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert (out / "rec_001" / "streams.json").exists()
    assert '"recorder"' in stats.read_text()  # the recorder's report is in the statistics


def test_record_with_a_taken_control_port_is_one_line_and_no_session(
    graph_file: Path, tmp_path: Path
) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        out = tmp_path / "out"
        r = flowrt_cli(
            "record", str(graph_file), "-o", str(out), "--no-ui", "--duration", "5",
            "--control", f"127.0.0.1:{port}",
        )  # fmt: skip
    assert r.returncode == 1, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith("flowrt record: control endpoint"), lines
    assert not any(out.glob("rec_*"))  # nothing ran, no empty session left


@pytest.mark.parametrize("bad", ["-1", "soon", "5 parsecs"])
def test_bad_duration_is_exit_2(graph_file: Path, tmp_path: Path, bad: str) -> None:
    for cmd in (["run", str(graph_file)], ["record", str(graph_file), "-o", str(tmp_path)]):
        r = flowrt_cli(*cmd, "--no-ui", "--duration", bad)
        assert r.returncode == 2, (cmd, r.stderr)
        assert "--duration" in r.stderr
        assert "Traceback" not in r.stderr


@pytest.mark.parametrize(
    ("width", "headers", "gone"),
    [
        (200, ["expected", "Hz mean", "Hz min", "Hz max", "bytes"], []),
        (80, ["expected", "received", "written", "lost", "missing"], ["Hz min", "Hz max"]),
        (64, ["received", "written", "lost"], ["expected", "bytes", "Hz mean"]),
    ],
)
def test_report_table_fits_the_terminal_and_never_cuts_a_name(
    width: int, headers: list[str], gone: list[str]
) -> None:
    import io

    from rich.console import Console

    from flowrt.recording import RecordingReport, report_table

    topic = "front_camera_with_a_long_name.frame"
    report = RecordingReport.model_validate(
        {
            "session": "rec_001", "files": ["rec_001.mcap"], "start_time": "now",
            "duration": 10.0, "error": None,
            "streams": [
                {
                    "topic": topic, "source": "cam.frame", "nominal_hz": 20.0, "expected": 200,
                    "received": 199, "written": 197, "lost": 2, "lost_behind": 2,
                    "lost_error": 0, "missing": 1, "rate_mean": 19.9, "rate_min": 18.1,
                    "rate_max": 21.7, "bytes": 123456789,
                }
            ],
        }
    )  # fmt: skip
    console = Console(width=width, file=io.StringIO(), color_system=None)
    console.print(report_table(report, width))
    text = console.file.getvalue()  # type: ignore[attr-defined]
    assert topic in text
    assert all(len(line) <= width for line in text.splitlines())
    for h in headers:
        assert h in text
    for h in gone:
        assert h not in text


@pytest.mark.parametrize(
    ("text", "seconds"),
    [("60", 60.0), ("90s", 90.0), ("2m", 120.0), ("500ms", 0.5), ("1.5min", 90.0), ("1h", 3600.0)],
)
def test_command_line_durations(text: str, seconds: float) -> None:
    from flowrt.cli.common import seconds_arg

    assert seconds_arg(text) == pytest.approx(seconds)


@pytest.mark.parametrize(
    ("formats", "topic", "fmt"),
    [
        ({"pair.set": "jpeg"}, "pair.set/a", "jpeg"),  # a set's member takes its set's
        ({"pair.set": "jpeg", "pair.set/b": "png"}, "pair.set/b", "png"),  # its own first
        ({"pair.set": "jpeg"}, "led.frame", "raw"),
        ({}, "pair.set/a", "raw"),
    ],
)
def test_a_sync_sets_frames_take_the_sets_image_format(
    formats: dict[str, str], topic: str, fmt: str
) -> None:
    """``--images jpeg`` left a set's frames raw (6.3 MiB against 123 KiB a stream)."""
    from flowrt.recording.ros2_profile import Ros2Encoder
    from flowrt.recording.streams import StreamBook

    assert StreamBook(formats).image_format(topic) == fmt
    assert Ros2Encoder(formats, 0.0)._format(topic, "raw") == fmt
