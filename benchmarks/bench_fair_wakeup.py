"""How late the fair scheduler wakes a high-priority periodic task, without SCHED_FIFO.

    python benchmarks/bench_fair_wakeup.py              # 6 configurations x 100 periods (~1 min)
    python benchmarks/bench_fair_wakeup.py --periods 40

Why this exists: flowrt without --realtime maps priorities to nice levels (by rank) and asks
EEVDF for short slices. This benchmark isolates the kernel's part, with no flowrt code in the
loop, to show what those tools can and cannot give on this machine.

Setup, all pinned to CPU 0 beside one ``while True: pass`` burner at nice 0 (a second burner
keeps CPU 1 busy): task **A** wakes every 50 ms at an absolute time and burns 3 ms (a
critical tracker); task **B**, when present, wakes 10 ms before A and burns 30 ms (a
lower-priority tracker in a long burst, so B is running when A wakes). Measured: A's wake-up
lateness (``time.monotonic()`` after ``clock_nanosleep`` returns, minus the due time).

Configurations: A alone vs the burner, with the default slice and with a 300 us slice; A
(nice -17) vs B (nice -11) with default slices, with A's slice shorter (100 us), with both
at 300 us; A (nice -17) vs B at nice +5; and, for reference, both SCHED_FIFO (45 and 35,
what --realtime gives). Each line prints p50/p99/max/std in ms.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from flowrt.system._priorities import request_short_slice  # noqa: E402


def task(nice: int, slice_us: int, burst_ms: float, offset: float, periods: int) -> None:
    """Run one periodic task in this process and print its wake-up lateness."""
    os.sched_setaffinity(0, {0})
    if nice >= 100:  # the reference: SCHED_FIFO priority nice - 100
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(nice - 100))
    else:
        os.setpriority(os.PRIO_PROCESS, 0, nice)
    if slice_us:
        request_short_slice(slice_us)
    late: list[float] = []
    due = (int(time.monotonic() * 20) + 4) / 20 + offset  # on a common 50 ms grid
    for _ in range(periods):
        time.sleep(max(0.0, due - time.monotonic()))
        late.append(time.monotonic() - due)
        end = time.monotonic() + burst_ms / 1000
        while time.monotonic() < end:
            pass
        due += 0.05
    ms = np.array(late[5:]) * 1e3
    print(
        f"p50 {np.median(ms):.3f}  p99 {np.percentile(ms, 99):.3f}  max {ms.max():.3f}  "
        f"std {ms.std():.3f}"
    )


@contextlib.contextmanager
def burners() -> Iterator[None]:
    procs = []
    for cpu in range(min(2, os.cpu_count() or 1)):
        code = f"import os; os.sched_setaffinity(0, {{{cpu}}})\nwhile True: pass"
        procs.append(subprocess.Popen([sys.executable, "-c", code]))
    try:
        time.sleep(0.5)
        yield
    finally:
        for p in procs:
            p.kill()
            p.wait()


def spawn(
    nice: int, slice_us: int, burst: float, offset: float, periods: int
) -> subprocess.Popen[str]:
    args = ["--task", str(nice), str(slice_us), str(burst), str(offset), str(periods)]
    return subprocess.Popen([sys.executable, __file__, *args], stdout=subprocess.PIPE, text=True)


CONFIGS: list[tuple[str, tuple[int, int], tuple[int, int] | None]] = [
    # label, (A nice, A slice us), (B nice, B slice us) or None
    ("A nice -17 alone, default slice", (-17, 0), None),
    ("A nice -17 alone, 300 us slice", (-17, 300), None),
    ("A nice -17 vs B nice -11, default slices", (-17, 0), (-11, 0)),
    ("A nice -17 (100 us slice) vs B nice -11 (default)", (-17, 100), (-11, 0)),
    ("A nice -17 vs B nice -11, both 300 us slices", (-17, 300), (-11, 300)),
    ("A nice -17 vs B nice +5, default slices", (-17, 0), (5, 0)),
    ("reference: A SCHED_FIFO 45 vs B SCHED_FIFO 35", (145, 0), (135, 0)),
]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--periods", type=int, default=100)
    ap.add_argument("--task", nargs=5, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.task:
        nice, slice_us, burst, offset, periods = args.task
        task(int(nice), int(slice_us), float(burst), float(offset), int(periods))
        return 0
    if os.getpriority(os.PRIO_PROCESS, 0) > -17 and os.geteuid() != 0:
        print("needs permission for nice -17 (root or RLIMIT_NICE)", file=sys.stderr)
        return 1
    print(f"kernel {os.uname().release}; A's wake-up lateness, ms")
    with burners():
        for label, (a_nice, a_slice), b in CONFIGS:
            b_proc = None if b is None else spawn(b[0], b[1], 30, -0.010, args.periods + 1)
            a_proc = spawn(a_nice, a_slice, 3, 0.0, args.periods)
            out, _ = a_proc.communicate()
            if b_proc is not None:
                b_proc.communicate()
            print(f"{label:52s} {out.strip()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
