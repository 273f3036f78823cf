"""flowrt's public face: the names it exports, pinned, and its lazy import.

anyio pins ``__all__`` with a test the same way: a name leaves or joins the public API on
purpose, in this file, never by a refactoring's side effect.
"""

from __future__ import annotations

import subprocess
import sys

import pytest

import flowrt

PUBLIC = [
    "RTDB",
    "AudioBlock",
    "Clock",
    "ControlConfig",
    "ControlServer",
    "DeadlineMissed",
    "Diagnostic",
    "DurationMs",
    "EdgeStats",
    "Event",
    "FatalError",
    "Frame",
    "FrameTrigger",
    "Graph",
    "GraphBuilder",
    "GraphError",
    "GraphSpec",
    "HealthAlert",
    "Input",
    "InputTrigger",
    "LoopBlocked",
    "LoopTrigger",
    "ModeChanged",
    "Monitor",
    "Node",
    "NodeContext",
    "NodeFailed",
    "NodeGaveUp",
    "NodeRestarted",
    "NodeStats",
    "NodeSwapped",
    "Output",
    "QosStatus",
    "Record",
    "Runtime",
    "RuntimeStats",
    "Subscription",
    "SwapError",
    "SystemClock",
    "TimerMs",
    "TimerTrigger",
    "TimingChanged",
    "VirtualClock",
    "parse_duration_ms",
    "replay",
    "resolve_path",
    "run",
]


def test_all_is_pinned() -> None:
    assert flowrt.__all__ == PUBLIC


def test_every_public_name_resolves_and_is_listed_by_dir() -> None:
    for name in [*PUBLIC, "__version__"]:
        assert getattr(flowrt, name) is not None, name
        assert name in dir(flowrt)
    assert flowrt.Runtime.__module__ == "flowrt.runtime._runtime"


def test_an_unknown_name_is_an_attribute_error() -> None:
    with pytest.raises(AttributeError, match="NoSuchThing"):
        flowrt.NoSuchThing  # type: ignore[attr-defined]  # noqa: B018


def test_import_flowrt_loads_neither_the_runtime_nor_the_http_server() -> None:
    """In a fresh interpreter: the face is lazy, the control server comes only when named."""
    probe = (
        "import sys, flowrt\n"
        "print(sorted(m for m in ('flowrt.runtime._runtime', 'flowrt.control.server', 'aiohttp') "
        "if m in sys.modules))\n"
        "flowrt.Runtime\n"
        "print('flowrt.control.server' in sys.modules, 'aiohttp' in sys.modules)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, check=True
    ).stdout.split("\n")
    assert out[0] == "[]", out
    assert out[1] == "False False", out


def test_version_comes_from_the_installed_metadata() -> None:
    from importlib.metadata import version

    assert flowrt.__version__ == version("flowrt")
