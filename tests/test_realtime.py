"""``--realtime``'s memory locking: locked as touched, never populated whole up front."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

pytestmark = pytest.mark.subprocess  # SCHED_FIFO and mlockall: in a process of its own

PROBE = textwrap.dedent(
    """
    import mmap, sys
    from flowrt.system._realtime import enable_realtime

    ok, what = enable_realtime()
    if not ok or "memory locked" not in what:
        print("SKIP", what)
        sys.exit(0)

    def rss_kib():
        with open("/proc/self/status") as f:
            return int(next(x for x in f if x.startswith("VmRSS")).split()[1])

    before = rss_kib()
    m = mmap.mmap(-1, 64 << 20)  # what the RTDB or a frame pool maps at run time
    print("GREW", rss_kib() - before)
    """
)


def test_realtime_memory_lock_does_not_populate_later_mappings() -> None:
    """A mapping made after ``enable_realtime`` costs nothing until it is touched: with
    mlockall's MCL_FUTURE alone the kernel populated all of it at once, on the thread that
    made it (the loop: ~6 ms for the RTDB at a run's first health alert)."""
    out = subprocess.run(
        [sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=60, check=True
    )
    if out.stdout.startswith("SKIP"):
        pytest.skip(f"no real-time scheduling here: {out.stdout.strip()}")
    grew_kib = int(out.stdout.split()[1])
    assert grew_kib < 16 << 10, f"64 MiB mapping made {grew_kib} KiB resident"
