"""Deterministic recording and replay: re-run a recorded run offline, every activation of every
processing node with exactly the inputs it had, and check that nothing changed.

A deterministic recording (``flowrt record G --deterministic``, or a ``recorder`` node with
``deterministic: true``) holds, beside the streams of a plain one, what makes the run
reproducible: the values every source published (with their sequence numbers and exact
times), every activation of every other node (release, start, the sequence number of the value
each input held), its completion, a digest of every output, and the changes made while it ran
(timing, params, restarts). Replay (``flowrt replay S --graph G --deterministic``) re-executes
those activations on a virtual clock, in the recorded order, as fast as the CPU allows.

- :mod:`.digest`: the canonical encoding of a value and its stable hash
- :mod:`.log`: what is recorded (topics, records) and reading it back from a session
- :mod:`.observer`: the scheduler's observer that writes the log during a run
- :mod:`.engine`: the virtual-time replay of the recorded activations
- :mod:`.report`: what a replay found (``--json``) and how it is said
- :mod:`.api`: ``flowrt.replay(...)``, the embedding API

The runtime never imports this package: the scheduler knows only an observer with three
methods (see :class:`.observer.Observer`), passed to it by the recorder through ``ctx.observe``.
"""

from .digest import canonical as canonical
from .digest import digest as digest
from .report import Divergence as Divergence
from .report import ReplayReport as ReplayReport

__all__ = ["Divergence", "ReplayReport", "canonical", "digest"]
