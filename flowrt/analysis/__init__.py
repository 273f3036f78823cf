"""Static analyses of timing: pure functions over graph models, no runtime imports.

One module per analysis: ``ticks`` (which nodes run on which tick over a hyperperiod).
"""

from .ticks import ActivationTable as ActivationTable
from .ticks import activation_tables as activation_tables

__all__ = ["ActivationTable", "activation_tables"]
