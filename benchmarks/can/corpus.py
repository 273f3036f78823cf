"""``flowrt can analyse`` over every DBC of the installed ``opendbc`` package.

    .venv/bin/python benchmarks/can/corpus.py [--json]

Prints how many files there are, how many cantools loads non-strictly, how many flowrt
analyses (exit 0 or 1) and refuses (exit 2, with cantools' reason), which strict-loading
warnings they carry (by reason), how many CAN FD and aperiodic messages they hold, and the
time the whole corpus takes. The figures of issue 27's closing note come from here.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import io
import json
import re
import sys
import time
from pathlib import Path
from typing import Any

from flowrt import cli


def run(path: Path) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = cli.main(["can", "analyse", str(path), "--json"])
    return rc, out.getvalue(), err.getvalue()


def _category(reason: str) -> str:
    """cantools' refusal, without the names and numbers of the file."""
    for key, label in (
        ("Invalid syntax", "invalid syntax"),
        ("unused VAL_", "unused VAL_ entries"),
        ("more than 11 bits", "a standard frame id of more than 11 bits"),
    ):
        if key in reason:
            return label
    return reason[:70]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    args = ap.parse_args()
    try:
        import opendbc
    except ImportError:
        print("opendbc is not installed (pip install opendbc)", file=sys.stderr)
        return 2
    files = sorted((Path(opendbc.__file__).parent / "dbc").rglob("*.dbc"))
    exits: collections.Counter[int] = collections.Counter()
    refused: collections.Counter[str] = collections.Counter()
    warnings: collections.Counter[str] = collections.Counter()
    files_with_warnings = fd_files = fd_msgs = aperiodic = messages = unschedulable = 0
    t0 = time.perf_counter()
    for path in files:
        rc, out, err = run(path)
        exits[rc] += 1
        if rc == 2:
            reason = err.split("not a valid CAN database:", 1)[-1].strip()
            refused[_category(reason)] += 1
            continue
        doc: dict[str, Any] = json.loads(out)
        unschedulable += rc == 1
        messages += len(doc["messages"])
        fd = [m for m in doc["messages"] if m["fd"]]
        fd_msgs += len(fd)
        fd_files += bool(fd)
        aperiodic += len(doc["not_analysed"])
        files_with_warnings += bool(doc["warnings"])
        for w in doc["warnings"]:
            warnings[re.sub(r"signal \S+", "signal X", w["reason"]).split("'")[0]] += 1
    figures = {
        "files": len(files),
        "analysed": exits[0] + exits[1],
        "schedulable": exits[0],
        "not_schedulable": unschedulable,
        "refused_by_cantools": exits[2],
        "refusals": dict(refused.most_common()),
        "messages": messages,
        "fd_files": fd_files,
        "fd_messages": fd_msgs,
        "not_analysed_messages": aperiodic,
        "files_with_strict_warnings": files_with_warnings,
        "strict_warnings": dict(warnings.most_common()),
        "seconds": round(time.perf_counter() - t0, 2),
    }
    if args.json:
        print(json.dumps(figures, indent=2))
    else:
        for key, value in figures.items():
            print(f"{key}: {value}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
