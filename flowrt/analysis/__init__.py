"""Static analyses of timing: pure functions over graph models, no runtime imports.

One module per analysis: ``ticks`` (which nodes run on which tick over a hyperperiod),
``rta`` (fixed-priority response-time analysis, preemptive and non-preemptive), ``timing``
(the timing view of a graph the analyses share, with budgets and run-time changes),
``schedulability`` (a whole graph on the loop, workers, pool and CPUs), ``load`` (summed
budget per tick), ``phases`` (phase advice), ``budgets`` (budgets from statistics),
``taskset`` (task-set files), ``admission`` (admission control of run-time changes).
"""

from .rta import Response as Response
from .rta import Task as Task
from .rta import response_times as response_times
from .schedulability import GraphVerdict as GraphVerdict
from .schedulability import analyse as analyse
from .ticks import ActivationTable as ActivationTable
from .ticks import activation_tables as activation_tables
from .timing import Budget as Budget
from .timing import graph_timing as graph_timing

__all__ = [
    "ActivationTable",
    "Budget",
    "GraphVerdict",
    "Response",
    "Task",
    "activation_tables",
    "analyse",
    "graph_timing",
    "response_times",
]
