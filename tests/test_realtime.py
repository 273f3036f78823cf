"""``--realtime``'s memory locking: locked as touched, never populated whole up front."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from typing import Any

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


REFUSED = textwrap.dedent(
    """
    import json, resource
    import flowrt

    resource.setrlimit(resource.RLIMIT_RTPRIO, (0, 0))

    async def main():
        g = flowrt.GraphBuilder("rt")
        g.add("tick", "counter", trigger={"timer": "10ms"})
        async with flowrt.Runtime(g.build(), realtime=True) as rt:
            await rt.run(0.1)
            s = rt.stats()
        print(json.dumps({"realtime": rt.realtime, "loop": s.loop_scheduling}))

    flowrt.run(main())
    """
)


def test_realtime_refused_keeps_the_fair_share() -> None:
    """--realtime where SCHED_FIFO is refused (no CAP_SYS_NICE, no rtprio limit): the loop
    still gets the nice-and-slice share it gets without the flag. Its refusal text started
    with "SCHED_FIFO", which the runtime took for a grant: no share at all."""
    import json
    import shutil

    setpriv = shutil.which("setpriv")
    if setpriv is None:
        pytest.skip("setpriv (util-linux) is needed to drop CAP_SYS_NICE")
    r = subprocess.run(
        [setpriv, "--inh-caps=-sys_nice", "--bounding-set=-sys_nice", sys.executable, "-c",
         REFUSED],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["realtime"].startswith("normal priority: SCHED_FIFO not permitted")
    assert "slice" in out["loop"], out


GRANTED = textwrap.dedent(
    """
    import json
    import flowrt

    class Tick(flowrt.Node):
        value = flowrt.Output(int)

        def process(self) -> int:
            return 1

    async def main():
        g = flowrt.GraphBuilder("rt")
        g.add("tick", Tick, trigger={"timer": "5ms"}, timing="precise", priority=60)
        async with flowrt.Runtime(g.build(), realtime=True) as rt:
            await rt.run(0.2)
            s = rt.stats()
        print(json.dumps({"realtime": rt.realtime, "granted": s.node("tick").granted}))

    if __name__ == "__main__":
        flowrt.run(main())
    """
)


def test_a_precise_thread_says_it_runs_at_the_loops_realtime_priority(tmp_path: Any) -> None:
    """With --realtime granted, the precise thread inherits the loop's SCHED_FIFO: the table
    said only "precise thread", as if it ran at the normal policy."""
    import json

    script = tmp_path / "granted.py"
    script.write_text(GRANTED)
    r = subprocess.run(
        [sys.executable, str(script)], capture_output=True, text=True, timeout=60, cwd=tmp_path
    )
    assert r.returncode == 0, r.stderr[-2000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    if not out["realtime"].startswith("SCHED_FIFO"):
        pytest.skip(f"SCHED_FIFO not granted here: {out['realtime']}")
    assert out["granted"].startswith("precise thread (SCHED_FIFO 90, the loop's)"), out
