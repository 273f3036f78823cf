"""Starting workers: the forkserver that preloads numpy and OpenCV, and the main script.

Workers are forked from a ``forkserver`` that has preloaded numpy and OpenCV, so their pages
are shared (copy-on-write) and a worker starts in milliseconds.
"""

from __future__ import annotations

import atexit
import contextlib
import multiprocessing
import multiprocessing.context
import multiprocessing.util
import os
import pickle
import signal
import socket
import sys
import threading
import weakref
from collections.abc import Mapping
from typing import Any

from ..ipc import PICKLE
from ..system import _spawned as spawned
from .errors import WorkerError

#: Blocked while the forkserver starts (see start_forkserver), ignored by it once preloaded.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)

#: Modules imported once by the forkserver, so every worker shares their pages.
PRELOAD_MODULES = [
    "numpy",
    "cv2",
    "flowrt.frames",
    "flowrt.frames.lending",
    "flowrt.system._priorities",
    "flowrt.workers",
    "flowrt.workers.child",
    # The node author's API and pydantic under it: what a worker imports when it unpickles a
    # node (import flowrt is lazy, so naming flowrt.workers no longer brings it along).
    "flowrt.node",
    "flowrt.events",
    "flowrt.workers._forkserver_signals",  # SIGTERM/SIGHUP ignored, inherited by every worker
    "flowrt.workers._forkserver_freeze",  # last: freezes all of the above before any fork
]


_ctx_lock = threading.Lock()
_ctx: multiprocessing.context.ForkServerContext | None = None


def context() -> multiprocessing.context.ForkServerContext:
    """The forkserver context, with numpy/cv2 preloaded (set before the server first starts)."""
    global _ctx
    with _ctx_lock:
        if _ctx is None:
            ctx = multiprocessing.get_context("forkserver")
            assert isinstance(ctx, multiprocessing.context.ForkServerContext)
            ctx.set_forkserver_preload(PRELOAD_MODULES)
            _ctx = ctx
        return _ctx


_open_ends: weakref.WeakSet[socket.socket] = weakref.WeakSet()
_shut_registered = False


def shut_at_exit(sock: socket.socket) -> None:
    """Shut ``sock``, the main process's end of a child's socket, down when the interpreter
    exits, before multiprocessing joins its children.

    Why: the children (workers, writer processes) ignore SIGTERM (``_forkserver_signals``),
    so multiprocessing's exit handler, which terminates daemonic children and then joins
    them, would wait forever for one whose socket is still open: a program that ends
    without stopping its runtime (an exception, ``sys.exit``) hung at exit. Shut down, the
    socket reads EOF in the child, which then exits as when the runtime dies. Atexit handlers
    run last registered first, and multiprocessing's is registered when ``multiprocessing.util``
    is imported (above), so this one runs before it.
    """
    global _shut_registered
    with _ctx_lock:
        if not _shut_registered:
            atexit.register(_shut_open_ends)
            _shut_registered = True
        _open_ends.add(sock)


def _shut_open_ends() -> None:
    for sock in list(_open_ends):
        with contextlib.suppress(OSError):  # closed already (a clean stop): nothing to do
            sock.shutdown(socket.SHUT_RDWR)


# Process names of workers that must not re-import the main script (see _install_prepare_hook).
NO_MAIN = "flowrt:"
WITH_MAIN = "flowrt+main:"
# Exit code of a worker whose import of the main script started a flowrt runtime again.
EXIT_MAIN_UNGUARDED = 78
_importing_main = False  # in a worker: re-running the main script to find the node's class


def exit_if_importing_main() -> None:
    """Where a runtime would start worker processes: refuse inside a worker's import of the
    main script, at once and quietly (the parent explains, from the exit code).

    Reaching this there means the script starts a runtime at import: it has no
    ``if __name__ == "__main__":`` guard. Letting it go on would start a runtime inside each
    worker, whose workers would do the same (multiprocessing stops that with a traceback in
    every attempt, and the node would crash-loop).
    """
    if _importing_main:
        os._exit(EXIT_MAIN_UNGUARDED)


def check_main_importable(node: str, factory: Any) -> bool:
    """True if the factory needs the main module; fatal if a worker could never import it.

    A class defined in ``python -c``, on stdin or in a notebook lives in a ``__main__`` that
    no other process can import: every start would fail the same way.
    """
    if not _needs_main(factory):
        return False
    main = sys.modules.get("__main__")
    if getattr(main, "__file__", None) is None and getattr(main, "__spec__", None) is None:
        raise WorkerError(
            node,
            "crashed",
            "its node class is defined in an interactive session (python -c, stdin, a "
            "notebook), which a worker process cannot import: define the class in a module "
            "or a script file, or use placement: inline",
            fatal=True,
        )
    return True


def unguarded_main_message() -> str:
    main = sys.modules.get("__main__")
    script = getattr(main, "__file__", None) or "the main script"
    return (
        f"its node class is defined in {script}, which starts a flowrt runtime "
        "again when a worker process imports it to load the class: put the code that starts "
        'the runtime under `if __name__ == "__main__":` (or define the node class in a module '
        "of its own)"
    )


def _install_prepare_hook() -> None:
    """Keep forkserver children from re-running the main script, unless the node lives there.

    multiprocessing re-imports ``__main__`` in every child so that objects defined in the main
    script unpickle. For a worker that is a waste at best (pytest, the CLI and their imports
    cost startup time and unshared memory in each of nine trackers) and a crash at worst (a
    script without a ``__main__`` guard). The hook runs in the forkserver (which preloads this
    module) and drops the main-module step for processes named ``flowrt:...``; a factory that
    is defined in ``__main__`` gets a ``flowrt+main:`` name and the usual behaviour.
    """
    from multiprocessing import spawn

    original = spawn.prepare
    if getattr(original, "_flowrt", False):
        return

    def prepare(data: Mapping[str, Any]) -> None:
        global _importing_main
        if str(data.get("name", "")).startswith(NO_MAIN):
            data = {
                k: v
                for k, v in data.items()
                if k not in ("init_main_from_path", "init_main_from_name")
            }
        _importing_main = True
        try:
            original(data)
        finally:
            _importing_main = False

    prepare._flowrt = True  # type: ignore[attr-defined]
    spawn.prepare = prepare


_install_prepare_hook()


def _needs_main(obj: Any) -> bool:
    """True if unpickling ``obj`` needs the main script's module."""
    try:
        return b"__main__" in pickle.dumps(obj, PICKLE)
    except Exception:
        return False


def start_forkserver() -> None:
    """Start the preloaded forkserver now (blocking, ~0.5 s the first time).

    The runtime calls this at start, before any deadline runs, so that the first worker start
    is not the one that pays for importing OpenCV.
    """
    from multiprocessing import forkserver

    exit_if_importing_main()
    context()
    # Python 3.11's forkserver runs ``python -c`` and ignores the sys.path it is given, so the
    # working directory comes first on its path: in the folder that holds a clone named
    # ``flowrt/``, the preloaded ``flowrt`` was that folder (a namespace package), and every
    # worker failed ("cannot import name 'Frame' from 'flowrt'"). PYTHONSAFEPATH (3.11+)
    # leaves the working directory out; workers get the main process's sys.path when they
    # start (multiprocessing's prepare), so user modules the main process can import work.
    before = os.environ.get("PYTHONSAFEPATH")
    os.environ["PYTHONSAFEPATH"] = "1"
    # The server starts with the stop signals blocked (a thread's signal mask is inherited
    # through fork and exec): multiprocessing ignores SIGINT there only after the preload,
    # so a Ctrl-C in its first second printed a traceback from inside numpy's import.
    # _forkserver_signals, preloaded, ignores them and unblocks (a pending one is dropped).
    try:
        with spawned.blocked(STOP_SIGNALS):
            forkserver.ensure_running()
    finally:
        if before is None:
            os.environ.pop("PYTHONSAFEPATH", None)
        else:
            os.environ["PYTHONSAFEPATH"] = before


# --------------------------------------------------------------------------------------------


def _set_pdeathsig() -> None:
    """Ask the kernel to SIGKILL this process when its parent (the forkserver) dies."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes

    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGKILL), 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def tied_to_runtime(main_pid: int) -> bool:
    """Start of a process the runtime forks (a worker, a recording writer): Ctrl-C and
    SIGTERM are the runtime's to handle, and the process dies with its parent; False when
    the runtime is already gone (it died while this process was being forked)."""
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)
    _set_pdeathsig()
    try:
        os.kill(main_pid, 0)
    except ProcessLookupError:
        return False
    return True
