"""Zenoh's threads take the loop's nice level (flowrt.remote._threads)."""

from __future__ import annotations

import os
import threading

import pytest

from flowrt.remote import _threads
from flowrt.remote._threads import ThreadShare


def _thread_at(nice: int, stop: threading.Event) -> tuple[threading.Thread, int]:
    got: list[int] = []
    ready = threading.Event()

    def run() -> None:
        os.setpriority(os.PRIO_PROCESS, 0, nice)  # this thread's own level (Linux)
        got.append(threading.get_native_id())
        ready.set()
        stop.wait(10)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    assert ready.wait(5)
    return t, got[0]


@pytest.mark.skipif(
    not os.path.isdir("/proc/self/task") or os.geteuid() != 0,
    reason="Linux, as root (lowering a thread's nice needs the privilege; CI has it)",
)
def test_threads_made_after_the_bridge_take_the_callers_nice_and_get_it_back(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    mine = os.getpriority(os.PRIO_PROCESS, 0)
    if mine > 10:
        pytest.skip("this thread's nice is too high to rank others below it")
    stop = threading.Event()
    try:
        older, older_tid = _thread_at(mine + 5, stop)  # an embedding program's own thread
        monkeypatch.setattr(_threads, "_BEFORE", None)  # as if this were the first session
        share = ThreadShare()
        newer, newer_tid = _thread_at(mine + 5, stop)  # as Zenoh's, made after
        share.share()
        assert os.getpriority(os.PRIO_PROCESS, newer_tid) == mine
        assert os.getpriority(os.PRIO_PROCESS, older_tid) == mine + 5  # untouched
        share.restore()
        assert os.getpriority(os.PRIO_PROCESS, newer_tid) == mine + 5
        again = ThreadShare()  # a later session: Zenoh's threads outlived the first one
        again.share()
        assert os.getpriority(os.PRIO_PROCESS, newer_tid) == mine
        assert os.getpriority(os.PRIO_PROCESS, older_tid) == mine + 5
        again.restore()
    finally:
        stop.set()
    older.join(5)
    newer.join(5)
