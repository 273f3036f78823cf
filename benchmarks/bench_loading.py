"""How fast an oversize or hostile graph file is refused, against PyYAML composing it.

The audit of issue 19 fed ``flowrt validate`` a 6 MB file of 100 000 nodes: it took 25 s and
632 MB to be refused. Now a file over 256 KiB is refused by its size before it is read, and
one that writes more than 50 000 values by libyaml's parser before Python composes it. The
baseline, in the same run: PyYAML's pure-Python ``yaml.compose`` of the same text (what the
loader did before), on a 1 MiB slice of the big file and on the whole value-heavy file.

Command: ``python benchmarks/bench_loading.py`` (a few seconds to a minute).
"""

from __future__ import annotations

import os
import platform
import tempfile
import time
from pathlib import Path

import yaml

from flowrt import Graph, GraphError


def _timed(fn: object) -> tuple[float, str]:
    t = time.perf_counter()
    try:
        fn()  # type: ignore[operator]
        outcome = "ok"
    except GraphError as e:
        outcome = str(e).split(": error: ", 1)[-1][:70]
    return time.perf_counter() - t, outcome


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        big = Path(tmp, "big.yaml")
        node = "  n{}:\n    kind: counter\n    trigger: {{timer: 10ms}}\n"
        big.write_text("nodes:\n" + "".join(node.format(i) for i in range(100_000)))
        values = Path(tmp, "values.yaml")
        values.write_text("[" + "1," * 126_000 + "1]\n")
        text = big.read_text()
        slice_1mib = text[: 1 << 20]
        slice_1mib = slice_1mib[: slice_1mib.rfind("\n  n")]
        rows = [
            (f"{big.stat().st_size / 2**20:.1f} MiB, 100 000 nodes", lambda: Graph.from_file(big)),
            (
                f"{values.stat().st_size / 2**10:.0f} KiB flow list, 126 001 values",
                lambda: Graph.from_file(values),
            ),
            (
                "baseline: yaml.compose (pure Python) of a 1 MiB slice of the big file",
                lambda: yaml.compose(slice_1mib, Loader=yaml.SafeLoader),
            ),
            (
                "baseline: yaml.compose (pure Python) of the flow list",
                lambda: yaml.compose(values.read_text(), Loader=yaml.SafeLoader),
            ),
        ]
        print(
            f"{platform.node()} · {os.cpu_count()} CPUs · Python {platform.python_version()} · "
            f"libyaml {yaml.__with_libyaml__} · load average {os.getloadavg()[0]:.2f} at start\n"
        )
        print("| file | seconds | outcome |\n|---|---:|---|")
        for name, fn in rows:
            seconds, outcome = _timed(fn)
            print(f"| {name} | {seconds:.3f} | {outcome} |")


if __name__ == "__main__":
    main()
