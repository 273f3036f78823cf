"""Worker processes: running a node outside the event loop (``placement: process`` / ``pool``).

A node placed in a worker is described by a picklable zero-argument *factory*; called in the
worker it returns an object with ``setup()``, ``process(**inputs)`` (a value or a coroutine,
which the worker runs to completion on its own event loop) and ``teardown()``. The node class is
the same whatever its placement.

Why processes: the GIL serialises Python threads, and the CAMBADA model needs the *kernel* to
preempt a low-priority tracker when a high-priority one becomes runnable. Each worker therefore
gets an OS priority from its flowrt priority (:mod:`flowrt.system._priorities`), and :attr:`granted`
reports what the kernel actually allowed.

Transport: one AF_UNIX stream socketpair per worker, length-prefixed pickles. The main side is
an asyncio protocol (works unchanged on asyncio and uvloop and never blocks the loop); the
worker side is a plain blocking socket. Frames from a :class:`~flowrt.frames.FramePool` pickle
to a descriptor of their shared-memory slot, so a 1080p frame costs the same as an integer.
Results are pickled back. A frame the node received and passes on goes back as its descriptor;
a frame it makes is written into a shared-memory slot the main process lent it with the call
(:mod:`flowrt.frames.lending`) and goes back as a descriptor too. Anything else (detections,
poses, a bare array) travels pickled.

Death detection: the process sentinel becomes readable when the worker exits for any reason
(exception escaping, segfault, abort, SIGKILL); EOF on the socket is seen as well. The in-flight
call fails with :class:`WorkerError` whose ``kind`` says what happened. A call running longer
than its watchdog is failed at that instant (kind ``hung``) and the worker is SIGKILLed,
unless the kernel says the worker was starved of CPU meanwhile (it waited on the run queue):
then the watchdog is extended and ``on_starved`` told, since killing it would not help.

Workers are forked from a ``forkserver`` that has preloaded numpy and OpenCV, so their pages
are shared (copy-on-write) and a worker starts in milliseconds. A worker dies with the runtime:
PR_SET_PDEATHSIG ties it to the forkserver, which exits when the main process does, and EOF on
its socket ends it too. Workers ignore SIGINT, SIGTERM and SIGHUP (sent to the whole process
group by Ctrl-C, ``kill`` of the group or a closed terminal): stopping is the main process's
business, which then stops them in order (SIGKILL still ends one, and it is replaced).
"""

from .errors import WorkerError, WorkerKind
from .executors import PoolExecutor, PoolNodeExecutor, ProcessExecutor, WorkerOptions
from .forkserver import PRELOAD_MODULES, start_forkserver

__all__ = [
    "PRELOAD_MODULES",
    "PoolExecutor",
    "PoolNodeExecutor",
    "ProcessExecutor",
    "WorkerError",
    "WorkerKind",
    "WorkerOptions",
    "start_forkserver",
]
