"""The test tiers, derived from what a test uses, and a guard that keeps the fast tier honest.

Two tiers: the fast one (``-m "not slow"``, what a developer runs on every change: no
process, nothing long) and everything (CI). A test is ``slow`` when it carries a tier marker
(:data:`TIERS`); the markers come from three places:

1. *Derived* (collection): a test's code, the fixtures it requests and the helpers of tests/
   they call (followed transitively, through classes too) are read for what starts a process:
   the ``subprocess`` and ``multiprocessing`` modules, asyncio's ``create_subprocess_*``,
   flowrt's worker and writer processes (``flowrt.workers``, ``ProcessRecordingWriter``),
   the servers that run in a process of their own (``ControlServer``, the ``Display``
   node), a graph that the test runs (``Runtime``, ``run``) and that names ``process`` or
   ``pool`` (a placement) or ``recorder``: ``subprocess``; Chromium (a ``chromium``
   executable named in the code): ``browser``; and any helper decorated with :func:`uses`.
   A new test that calls ``flowrt_cli`` is slow without anyone remembering to say so.
2. *Declared* (``pytest.mark.realtime`` and the like, or ``pytestmark`` in a file): what
   cannot be read from the code, a test that measures real time or whose graph places a node
   in a worker process (the graph file says so, not the test's code).
3. *The guard* (run time): a test left in the fast tier that starts a process anyway (a
   worker from its graph, a forkserver, a program) fails with a line naming what it started
   and the marker to add; so does one that costs more than :data:`FAST_SECONDS`.

The 1 s rule on a loaded machine: the guard measures the *CPU time* of the test's process
(every thread), which a busy machine does not inflate: a test given 0.3 s of CPU still uses
0.3 s when it waits twice as long for it. Real sleeps use no CPU, so the wall clock is checked
too, twice generously: the test fails only when it took more than ``FAST_SECONDS`` x max(3,
load average / CPUs) (3 s on an idle machine, 25 s at a load of 16 on 2 cores) *and* its
thread slept more than 3 x ``FAST_SECONDS`` of it: the wall clock minus what the kernel says
the thread ran and waited on the run queue (``/proc/self/task/TID/schedstat``), so waiting
for a CPU that other programs hold is not taken for sleeping. A test that sleeps for seconds
is caught; one that a busy machine merely slowed is not.
``FLOWRT_FAST_SECONDS`` changes the limit (0: no timing check; processes are always checked).
"""

from __future__ import annotations

import asyncio
import functools
import inspect
import multiprocessing
import multiprocessing.process
import multiprocessing.util
import os
import subprocess
import sys
import threading
import time
import types
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, TypeVar

import pytest

TESTS = Path(__file__).resolve().parent
TIERS = ("browser", "subprocess", "realtime", "node")
FAST_SECONDS = float(os.environ.get("FLOWRT_FAST_SECONDS", "1"))
#: A hypothesis test's CPU limit, in FAST_SECONDS (see :func:`verdict`).
HYPOTHESIS_FACTOR = 4
SLEEP_FACTOR = 3.0  # of FAST_SECONDS: asleep on the real clock

# What in a test's code starts a process. Modules by name; flowrt's own process owners by the
# module they come from; names that are distinctive wherever they appear (an attribute:
# ``asyncio.create_subprocess_exec``).
PROCESS_MODULES = ("subprocess", "multiprocessing", "asyncio.subprocess")
PROCESS_OBJECTS = frozenset(
    {
        "flowrt.workers.channel.Worker",
        "flowrt.workers.executors.PoolExecutor",
        "flowrt.workers.executors.PoolNodeExecutor",
        "flowrt.workers.executors.ProcessExecutor",
        "flowrt.workers.forkserver.start_forkserver",
        "flowrt.recording.writer.channel.ProcessRecordingWriter",
        "flowrt.control.server.ControlServer",  # serves from a process of its own
        "flowrt.nodes.station.display.Display",  # its view server: a process of its own
    }
)
# String constants that put a process in a test's graph: a node placed in a worker or the
# pool, a recorder (its writer is a process by default). Exact values, in the test's code or
# its parameters (``@pytest.mark.parametrize("placement", ["process", "inline"])``).
PROCESS_STRINGS = frozenset({"process", "pool", "recorder"})
# ...which matter only when the test runs a graph (a test of validation or of the status
# table names placements without starting anything).
RUNNERS = frozenset({"Runtime", "run", "replay"})
_NAMES_A_PROCESS, _RUNS = "?process-string", "?runs"  # clues, combined by derive()
PROCESS_NAMES = frozenset(
    {"create_subprocess_exec", "create_subprocess_shell", "Popen", "ProcessRecordingWriter"}
)

F = TypeVar("F", bound=Callable[..., Any])


def uses(*tiers: str) -> Callable[[F], F]:
    """Mark a helper or fixture with what it uses: every test that calls it is tiered so."""
    unknown = set(tiers) - set(TIERS)
    assert not unknown, f"unknown tiers {unknown}: one of {TIERS}"

    def mark(fn: F) -> F:
        fn.__flowrt_tiers__ = tuple(tiers)  # type: ignore[attr-defined]
        return fn

    return mark


# -- derived at collection --------------------------------------------------------------------


_TESTS_PREFIX = str(TESTS) + os.sep


@functools.cache
def _file_in_tests(filename: str) -> bool:
    return os.path.abspath(filename).startswith(_TESTS_PREFIX)


def _in_tests(obj: Any) -> bool:
    code = getattr(obj, "__code__", None)
    return code is not None and _file_in_tests(code.co_filename)


def _codes(code: types.CodeType) -> Iterable[types.CodeType]:
    """A code object and those nested in it (inner functions, comprehensions, lambdas)."""
    yield code
    for const in code.co_consts:
        if isinstance(const, types.CodeType):
            yield from _codes(const)


def _of_object(obj: Any) -> set[str]:
    """Tiers a global a test names implies on its own (without reading its code)."""
    found = set(getattr(obj, "__flowrt_tiers__", ()))
    if isinstance(obj, types.ModuleType):
        if obj.__name__ in PROCESS_MODULES:
            found.add("subprocess")
    else:
        module = getattr(obj, "__module__", None) or ""
        qualified = f"{module}.{getattr(obj, '__qualname__', '')}"
        if module.startswith(PROCESS_MODULES) or qualified in PROCESS_OBJECTS:
            found.add("subprocess")
    return found


def tiers_used(fn: Any, seen: set[int] | None = None) -> set[str]:
    """What ``fn`` (a test, fixture or helper of tests/) uses, transitively."""
    seen = set() if seen is None else seen
    fn = inspect.unwrap(fn)
    if id(fn) in seen:
        return set()
    seen.add(id(fn))
    found = set(getattr(fn, "__flowrt_tiers__", ()))
    if isinstance(fn, type):  # a helper class of tests/: its methods
        for member in vars(fn).values():
            member = getattr(member, "__func__", member)
            if _in_tests(member):
                found |= tiers_used(member, seen)
        return found
    code = getattr(fn, "__code__", None)
    if code is None:
        return found
    glob = getattr(fn, "__globals__", {})
    for c in _codes(code):
        strings = [k for k in c.co_consts if isinstance(k, str)]
        if any("chromium" in k for k in strings):
            found.add("browser")
        if PROCESS_STRINGS.intersection(strings):
            found.add(_NAMES_A_PROCESS)
        if RUNNERS.intersection(c.co_names):
            found.add(_RUNS)
        for name in c.co_names:
            if name in PROCESS_NAMES or name in PROCESS_MODULES:  # (imported in a function too)
                found.add("subprocess")
            if name not in glob:
                continue
            obj = glob[name]
            if callable(obj) and not isinstance(obj, type):
                obj = inspect.unwrap(obj)  # a helper behind a decorator (a context manager)
            found |= _of_object(obj)
            if _in_tests(obj) or (isinstance(obj, type) and obj.__module__ in _test_modules()):
                found |= tiers_used(obj, seen)
    return found


def _test_modules() -> set[str]:
    global _modules
    if _modules is None:
        _modules = {
            name
            for name, mod in list(sys.modules.items())
            if (f := getattr(mod, "__file__", None)) and _file_in_tests(f)
        }
    return _modules


_modules: set[str] | None = None  # the modules of tests/, once collection has imported them


def derive(items: list[pytest.Item]) -> None:
    """Mark each test with the tiers its code and fixtures use; every tier implies slow."""
    global _modules
    _modules = None
    known: dict[int, set[str]] = {}  # a test function or fixture read once, however often used

    def read(fn: Any) -> set[str]:
        if id(fn) not in known:
            known[id(fn)] = tiers_used(fn)
        return known[id(fn)]

    for item in items:
        found: set[str] = set()
        fn = getattr(item, "obj", None)
        if fn is not None:
            found |= read(fn)
        callspec = getattr(item, "callspec", None)
        if callspec is not None and any(
            isinstance(v, str) and v in PROCESS_STRINGS for v in callspec.params.values()
        ):
            found.add(_NAMES_A_PROCESS)
        info = getattr(item, "_fixtureinfo", None)
        for defs in info.name2fixturedefs.values() if info is not None else ():
            for fixturedef in defs:
                found |= read(fixturedef.func)
        if {_NAMES_A_PROCESS, _RUNS} <= found:
            found.add("subprocess")
        for tier in sorted(found - {_NAMES_A_PROCESS, _RUNS}):
            if item.get_closest_marker(tier) is None:
                item.add_marker(getattr(pytest.mark, tier))
        if any(item.get_closest_marker(t) is not None for t in TIERS):
            item.add_marker(pytest.mark.slow)


# -- the guard, at run time -------------------------------------------------------------------

_started: list[str] | None = None  # processes started by the running test (None: no test)


def _note(what: str) -> None:
    if _started is not None:
        _started.append(what)


def _wrap(owner: Any, name: str, describe: Callable[..., str]) -> None:
    original = getattr(owner, name)
    if getattr(original, "__flowrt_guard__", False):
        return

    def guarded(*args: Any, **kwargs: Any) -> Any:
        _note(describe(*args, **kwargs))
        return original(*args, **kwargs)

    guarded.__flowrt_guard__ = True  # type: ignore[attr-defined]
    guarded.__wrapped__ = original  # type: ignore[attr-defined]
    setattr(owner, name, guarded)


def _argv(args: Any) -> str:
    if isinstance(args, str | bytes):
        return str(args)[:60]
    return " ".join(str(a) for a in list(args)[:4])[:60]


def install_guard() -> None:
    """Hear of every process started in this process, whichever way it is started."""
    _wrap(
        subprocess.Popen,
        "_execute_child",
        lambda self, args, *a, **k: f"a program ({_argv(args)})",
    )
    _wrap(
        multiprocessing.process.BaseProcess,
        "start",
        lambda self: f"a process ({self.name})",
    )
    _wrap(multiprocessing.util, "spawnv_passfds", lambda path, args, passfds: "a forkserver")
    for mod in (asyncio, asyncio.subprocess):
        _wrap(mod, "create_subprocess_exec", lambda *a, **k: f"a program ({_argv(a[:4])})")
        _wrap(mod, "create_subprocess_shell", lambda cmd, **k: f"a shell ({_argv(cmd)})")
    for name in ("posix_spawn", "posix_spawnp", "system"):
        if hasattr(os, name):
            _wrap(os, name, lambda first, *a, **k: f"a program ({_argv([first])})")
    os.register_at_fork(before=lambda: _note("a fork"))


def _scheduled() -> float | None:
    """Seconds this thread has run or waited for a CPU (Linux schedstat), else None."""
    try:
        with open(f"/proc/self/task/{threading.get_native_id()}/schedstat") as f:
            run_ns, wait_ns, _ = f.read().split()
    except (OSError, ValueError):
        return None
    return (int(run_ns) + int(wait_ns)) / 1e9


def _wall_limit() -> float:
    try:
        load = os.getloadavg()[0] / (os.cpu_count() or 1)
    except OSError:
        load = 1.0
    return FAST_SECONDS * max(3.0, load)


def is_slow(item: pytest.Item) -> bool:
    return item.get_closest_marker("slow") is not None


def start(item: pytest.Item) -> None:
    global _started
    _started = []
    item.stash[_clock] = (time.process_time(), time.monotonic(), _scheduled())


def stop() -> None:
    global _started
    _started = None


_clock = pytest.StashKey[tuple[float, float, float | None]]()


def verdict(item: pytest.Item) -> str | None:
    """Why a fast-tier test does not belong there (setup and call so far), or None."""
    if is_slow(item) or _clock not in item.stash:
        return None
    if _started:
        what = ", ".join(dict.fromkeys(_started))
        return (
            f"a fast-tier test started {what}: mark it @pytest.mark.subprocess (or use a "
            "helper marked with tiers.uses), so that `pytest -m 'not slow'` starts no process"
        )
    if FAST_SECONDS <= 0:
        return None
    cpu0, wall0, sched0 = item.stash[_clock]
    cpu, wall = time.process_time() - cpu0, time.monotonic() - wall0
    # A property test's cost varies with the examples drawn (a fresh clone has no example
    # database): 1.0-1.3 s of CPU seen for the same test; its limit is HYPOTHESIS_FACTOR times.
    hypothesis = getattr(getattr(item, "obj", None), "is_hypothesis_test", False)
    cpu_limit = FAST_SECONDS * (HYPOTHESIS_FACTOR if hypothesis else 1)
    if cpu > cpu_limit:
        return (
            f"a fast-tier test used {cpu:.1f} s of CPU (limit {cpu_limit:g} s): make it "
            "smaller, or mark it slow"
        )
    limit = _wall_limit()
    if wall <= limit:
        return None
    sched1 = _scheduled()
    slept = wall if sched0 is None or sched1 is None else wall - (sched1 - sched0)
    if slept > SLEEP_FACTOR * FAST_SECONDS:
        return (
            f"a fast-tier test took {wall:.1f} s (limit {limit:.1f} s at this load), "
            f"{slept:.1f} s of it asleep (CPU {cpu:.1f} s): it waits on the real clock: mark "
            "it @pytest.mark.realtime"
        )
    return None
