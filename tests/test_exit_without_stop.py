"""A program that ends with its runtime still running (an exception, ``sys.exit``) exits.

Its worker and writer processes ignore SIGTERM (the runtime stops them in order), so
multiprocessing's exit handler, which terminates daemonic children and then joins them, waited
forever for any of them still connected: a program with a recorder's writer process hung at
exit (a worker's socket happened to be closed with the event loop; it is kept beside as a
guard). Each case: a program that starts a runtime with such a child, runs half a second and
calls ``sys.exit(3)``.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

pytestmark = [pytest.mark.slow, pytest.mark.subprocess]

PROGRAM = """
import asyncio, sys
import flowrt
from flowrt import GraphBuilder

async def main() -> None:
    g = GraphBuilder("left-running")
    g.add("cam", "capture", params={{"source": "synthetic:soccer", "fps": 20, "size": [64, 48]}})
    {node}
    rt = flowrt.Runtime(g.build())
    await rt.start()
    await rt.run(0.5)
    sys.exit(3)  # no rt.stop(): the program ends with the runtime running

if __name__ == "__main__":
    flowrt.run(main())
"""

CHILDREN = {
    "writer process": 'g.add("rec", "recorder", params={"path": sys.argv[1], "writer": "process"},'
    ' inputs={"cam": "cam.frame"})',
    "worker": 'g.add("ball", "tracker", params={"object": "ball"}, inputs={"frame": "cam.frame"},'
    ' placement="process")',
}


@pytest.mark.parametrize("child", list(CHILDREN))
def test_a_program_that_ends_without_stopping_its_runtime_exits(tmp_path: Path, child: str) -> None:
    script = tmp_path / "prog.py"
    script.write_text(textwrap.dedent(PROGRAM.format(node=CHILDREN[child])))
    r = subprocess.run(
        [sys.executable, str(script), str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=60,  # it hung for good before
        cwd=tmp_path,
    )
    assert r.returncode == 3, r.stderr[-2000:]
