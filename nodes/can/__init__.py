"""The ``can`` and ``can-signals`` node kinds: a bus, a database, decoded signals."""

from .node import Can as Can
from .node import SignalSource as SignalSource
