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
    from .builder import GraphBuilder as GraphBuilder
    from .clock import Clock as Clock
    from .clock import SystemClock as SystemClock
    from .clock import VirtualClock as VirtualClock
    from .control import ControlConfig as ControlConfig
    from .control import ControlServer as ControlServer
    from .determinism.api import replay as replay
    from .diagnostics import Diagnostic as Diagnostic
    from .diagnostics import GraphError as GraphError
    from .eventloop import run as run
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
    from .graph import Graph as Graph
    from .graph import resolve_path as resolve_path
    from .node import FatalError as FatalError
    from .node import Input as Input
    from .node import Node as Node
    from .node import NodeContext as NodeContext
    from .node import Output as Output
    from .qos import QosStatus as QosStatus
    from .rtdb import RTDB as RTDB
    from .rtdb import Record as Record
    from .runtime import Monitor as Monitor
    from .runtime import Runtime as Runtime
    from .runtime import SwapError as SwapError
    from .spec import DurationMs as DurationMs
    from .spec import FrameTrigger as FrameTrigger
    from .spec import GraphSpec as GraphSpec
    from .spec import InputTrigger as InputTrigger
    from .spec import LoopTrigger as LoopTrigger
    from .spec import TimerMs as TimerMs
    from .spec import TimerTrigger as TimerTrigger
    from .spec import parse_duration_ms as parse_duration_ms
    from .stats import EdgeStats as EdgeStats
    from .stats import NodeStats as NodeStats
    from .stats import RuntimeStats as RuntimeStats
    from .subscription import Subscription as Subscription
    from .version import __version__ as __version__

# name -> (module, attribute): imported on first use
_LAZY: dict[str, tuple[str, str]] = {
    "AudioBlock": (".audio", "AudioBlock"),
    "GraphBuilder": (".builder", "GraphBuilder"),
    "Clock": (".clock", "Clock"),
    "SystemClock": (".clock", "SystemClock"),
    "VirtualClock": (".clock", "VirtualClock"),
    "ControlConfig": (".control", "ControlConfig"),
    "ControlServer": (".control", "ControlServer"),
    "replay": (".determinism.api", "replay"),
    "Diagnostic": (".diagnostics", "Diagnostic"),
    "GraphError": (".diagnostics", "GraphError"),
    "run": (".eventloop", "run"),
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
    "Graph": (".graph", "Graph"),
    "resolve_path": (".graph", "resolve_path"),
    "FatalError": (".node", "FatalError"),
    "Input": (".node", "Input"),
    "Node": (".node", "Node"),
    "NodeContext": (".node", "NodeContext"),
    "Output": (".node", "Output"),
    "QosStatus": (".qos", "QosStatus"),
    "RTDB": (".rtdb", "RTDB"),
    "Record": (".rtdb", "Record"),
    "Monitor": (".runtime", "Monitor"),
    "Runtime": (".runtime", "Runtime"),
    "SwapError": (".runtime", "SwapError"),
    "DurationMs": (".spec", "DurationMs"),
    "FrameTrigger": (".spec", "FrameTrigger"),
    "GraphSpec": (".spec", "GraphSpec"),
    "InputTrigger": (".spec", "InputTrigger"),
    "LoopTrigger": (".spec", "LoopTrigger"),
    "TimerMs": (".spec", "TimerMs"),
    "TimerTrigger": (".spec", "TimerTrigger"),
    "parse_duration_ms": (".spec", "parse_duration_ms"),
    "EdgeStats": (".stats", "EdgeStats"),
    "NodeStats": (".stats", "NodeStats"),
    "RuntimeStats": (".stats", "RuntimeStats"),
    "Subscription": (".subscription", "Subscription"),
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
