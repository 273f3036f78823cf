"""flowrt: a real-time dataflow runtime for robot perception and control."""

from . import _startup  # noqa: F401  (first: Ctrl-C while the flowrt command imports)
from .audio import AudioBlock as AudioBlock
from .builder import GraphBuilder as GraphBuilder
from .clock import Clock as Clock
from .clock import SystemClock as SystemClock
from .clock import VirtualClock as VirtualClock
from .control import ControlConfig as ControlConfig
from .control import ControlServer as ControlServer
from .determinism.api import replay as replay  # after the runtime: it builds on it
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
