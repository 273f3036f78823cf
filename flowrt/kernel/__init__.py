"""The kernel: runners, their scheduler, and the parts they are made of.

A newcomer finds each concept by file name: ``scheduler`` (frame clocks, timers, dispatch),
``runner`` (one node's releases and values), ``activation`` (the frame links one run holds),
``deadlines``, ``pipeline`` (overlapping worker calls), ``backpressure`` (full lossless
readers), ``supervisor`` (failures, restarts), ``swapping``, ``counters`` (and statistics),
``drain`` (the end of a run), ``executor`` (where ``process`` runs), ``context`` (a node's
``ctx``), ``services`` (what the runtime hands the kernel), ``state`` (the runner's states),
``views`` (what a node looks like from outside the kernel).
"""

from .executor import Executor, InlineExecutor
from .runner import NodeRunner
from .scheduler import Scheduler
from .services import FramePort, Services, WorkerPort
from .state import RunState
from .views import NodeView

__all__ = [
    "Executor",
    "FramePort",
    "InlineExecutor",
    "NodeRunner",
    "NodeView",
    "RunState",
    "Scheduler",
    "Services",
    "WorkerPort",
]
