"""Total PSS of a running graph: the main process plus every worker (issue 3's memory target).

    python benchmarks/bench_memory.py [graphs/cambada.yaml] [--settle 5]

Starts ``flowrt run GRAPH --no-ui`` as a subprocess, lets it settle, then sums the
proportional set size (PSS: shared pages split between the processes that map them) of the
runtime process and all its descendants (forkserver and workers), as a markdown table.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time

import psutil


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("graph", nargs="?", default="graphs/cambada.yaml")
    ap.add_argument("--settle", type=float, default=5.0, help="seconds to run before measuring")
    args = ap.parse_args()
    proc = subprocess.Popen(
        ["flowrt", "run", args.graph, "--no-ui", "--log-every", "1000"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        time.sleep(args.settle)
        main_proc = psutil.Process(proc.pid)
        rows = []
        for p in [main_proc, *main_proc.children(recursive=True)]:
            try:
                info = p.memory_full_info()
                if p.ppid() != proc.pid:
                    role = "worker"
                elif any("resource_tracker" in a for a in p.cmdline()):
                    role = "resource tracker"
                else:
                    role = "forkserver"
                rows.append((p.pid, role, info.pss, info.rss))
            except psutil.Error:
                continue
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=30)
    mb = 1024 * 1024
    print(
        f"graph: {args.graph}, {len(rows)} processes, "
        f"Python {sys.version.split()[0]}, pid {os.getpid()}"
    )
    print()
    print("| process | PSS MB | RSS MB |")
    print("|---|---:|---:|")
    for pid, name, pss, rss in rows:
        label = "main (event loop)" if pid == proc.pid else name
        print(f"| {label} | {pss / mb:.1f} | {rss / mb:.1f} |")
    print(
        f"| **total** | **{sum(r[2] for r in rows) / mb:.1f}** "
        f"| {sum(r[3] for r in rows) / mb:.1f} |"
    )


if __name__ == "__main__":
    main()
