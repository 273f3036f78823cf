"""Imported by the workers' forkserver only: stopping is the main process's business.

SIGTERM (systemd, ``kill`` of the process group) and SIGHUP (terminal closed) reach every
process of the group at once. Had the forkserver and the workers died of them, the runtime
would have seen every worker crash during its own orderly stop (tracebacks, "Future exception
was never retrieved") and no node's ``teardown`` would have run in its worker. So they ignore
them, as they ignore SIGINT (Ctrl-C); the main process stops the workers in order, and they
die with it anyway (EOF on their socket, PR_SET_PDEATHSIG). SIGKILL still ends a worker, and
the runtime replaces it.

The server started with the three blocked (:func:`flowrt.workers.forkserver.start_forkserver`):
one sent while it imported numpy and OpenCV is pending; ignoring drops it, then they are
unblocked, for the workers too (they inherit the mask, and so would their own children).
"""

from ..system._spawned import ignore
from .forkserver import STOP_SIGNALS

ignore(STOP_SIGNALS)
