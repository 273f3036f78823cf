"""flowrt: a real-time dataflow runtime for robot perception and control.

The public face, imported lazily (as anyio's): ``import flowrt`` loads nothing but this
table, and ``flowrt.Runtime`` imports the runtime the first time it is named. A program that
only builds graphs, or a worker process, does not pay for the runtime, and nobody pays for
the HTTP control server (``aiohttp``) until ``flowrt.ControlServer`` is asked for.
``__all__`` is pinned by tests/test_public_api.py: a name added here is added there.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from . import _startup  # noqa: F401  (first: Ctrl-C while the flowrt command imports)

if TYPE_CHECKING:  # what type checkers and editors see; at run time: __getattr__ below
    from .audio import AudioBlock as AudioBlock
    from .clock import Clock as Clock
    from .clock import SystemClock as SystemClock
    from .clock import VirtualClock as VirtualClock
    from .control.server import ControlConfig as ControlConfig
    from .control.server import ControlServer as ControlServer
    from .determinism.api import replay as replay
    from .events import DeadlineMissed as DeadlineMissed
    from .events import Event as Event
    from .events import HealthAlert as HealthAlert
    from .events import LoopBlocked as LoopBlocked
    from .events import ModeChanged as ModeChanged
    from .events import NodeFailed as NodeFailed
    from .events import NodeGaveUp as NodeGaveUp
    from .events import NodeRestarted as NodeRestarted
    from .events import NodeSwapped as NodeSwapped
    from .events import TimingChanged as TimingChanged
    from .frames import Frame as Frame
    from .graph._builder import GraphBuilder as GraphBuilder
    from .graph._resolve import Graph as Graph
    from .graph._resolve import resolve_path as resolve_path
    from .graph.diagnostics import Diagnostic as Diagnostic
    from .graph.diagnostics import GraphError as GraphError
    from .graph.spec import DurationMs as DurationMs
    from .graph.spec import FrameTrigger as FrameTrigger
    from .graph.spec import GraphSpec as GraphSpec
    from .graph.spec import InputTrigger as InputTrigger
    from .graph.spec import LoopTrigger as LoopTrigger
    from .graph.spec import TimerMs as TimerMs
    from .graph.spec import TimerTrigger as TimerTrigger
    from .graph.spec import parse_duration_ms as parse_duration_ms
    from .node import FatalError as FatalError
    from .node import Input as Input
    from .node import Node as Node
    from .node import NodeContext as NodeContext
    from .node import Output as Output
    from .rtdb import RTDB as RTDB
    from .rtdb import Record as Record
    from .runtime._qos import QosStatus as QosStatus
    from .runtime._runtime import Monitor as Monitor
    from .runtime._runtime import Runtime as Runtime
    from .runtime._runtime import SwapError as SwapError
    from .runtime._subscription import Subscription as Subscription
    from .stats import EdgeStats as EdgeStats
    from .stats import NodeStats as NodeStats
    from .stats import RuntimeStats as RuntimeStats
    from .system._eventloop import run as run
    from .version import __version__ as __version__

# name -> (module, attribute): imported on first use
_LAZY: dict[str, tuple[str, str]] = {
    "AudioBlock": (".audio", "AudioBlock"),
    "GraphBuilder": (".graph._builder", "GraphBuilder"),
    "Clock": (".clock", "Clock"),
    "SystemClock": (".clock", "SystemClock"),
    "VirtualClock": (".clock", "VirtualClock"),
    "ControlConfig": (".control.server", "ControlConfig"),
    "ControlServer": (".control.server", "ControlServer"),
    "replay": (".determinism.api", "replay"),
    "Diagnostic": (".graph.diagnostics", "Diagnostic"),
    "GraphError": (".graph.diagnostics", "GraphError"),
    "run": (".system._eventloop", "run"),
    "DeadlineMissed": (".events", "DeadlineMissed"),
    "Event": (".events", "Event"),
    "HealthAlert": (".events", "HealthAlert"),
    "LoopBlocked": (".events", "LoopBlocked"),
    "ModeChanged": (".events", "ModeChanged"),
    "NodeFailed": (".events", "NodeFailed"),
    "NodeGaveUp": (".events", "NodeGaveUp"),
    "NodeRestarted": (".events", "NodeRestarted"),
    "NodeSwapped": (".events", "NodeSwapped"),
    "TimingChanged": (".events", "TimingChanged"),
    "Frame": (".frames", "Frame"),
    "Graph": (".graph._resolve", "Graph"),
    "resolve_path": (".graph._resolve", "resolve_path"),
    "FatalError": (".node", "FatalError"),
    "Input": (".node", "Input"),
    "Node": (".node", "Node"),
    "NodeContext": (".node", "NodeContext"),
    "Output": (".node", "Output"),
    "QosStatus": (".runtime._qos", "QosStatus"),
    "RTDB": (".rtdb", "RTDB"),
    "Record": (".rtdb", "Record"),
    "Monitor": (".runtime._runtime", "Monitor"),
    "Runtime": (".runtime._runtime", "Runtime"),
    "SwapError": (".runtime._runtime", "SwapError"),
    "DurationMs": (".graph.spec", "DurationMs"),
    "FrameTrigger": (".graph.spec", "FrameTrigger"),
    "GraphSpec": (".graph.spec", "GraphSpec"),
    "InputTrigger": (".graph.spec", "InputTrigger"),
    "LoopTrigger": (".graph.spec", "LoopTrigger"),
    "TimerMs": (".graph.spec", "TimerMs"),
    "TimerTrigger": (".graph.spec", "TimerTrigger"),
    "parse_duration_ms": (".graph.spec", "parse_duration_ms"),
    "EdgeStats": (".stats", "EdgeStats"),
    "NodeStats": (".stats", "NodeStats"),
    "RuntimeStats": (".stats", "RuntimeStats"),
    "Subscription": (".runtime._subscription", "Subscription"),
    "__version__": (".version", "__version__"),
}

__all__ = [
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


def __getattr__(name: str) -> Any:
    try:
        module, attr = _LAZY[name]
    except KeyError:
        raise AttributeError(f"module 'flowrt' has no attribute {name!r}") from None
    value = getattr(importlib.import_module(module, __name__), attr)
    globals()[name] = value  # once: later reads are plain attribute reads
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_LAZY})
