"""``flowrt examples``: the example graphs that ship with flowrt, listed or written out.

A clone of the repository has them in ``graphs/``; a wheel installed from a package index has
no such folder, so the README's ``flowrt run graphs/cambada.yaml`` had nothing to run. They
ship inside the package (``flowrt.examples``, mapped from ``graphs/`` by setup.py) with the
files they name (relative paths resolve against a graph file's folder): ``flowrt examples
--copy .`` writes ``./graphs/`` as the clone has it, and the README's commands work there.
"""

from __future__ import annotations

import argparse
import sys
from importlib.abc import Traversable
from pathlib import Path
from typing import Any

from .common import EXIT_BAD_GRAPH, EXIT_FAILED, EXIT_OK, stdout_console
from .example_files import shipped
from .json_output import emit


def _summary(graph: Traversable, width: int) -> str:
    """The first sentence of the graph's leading comment, cut to ``width`` characters."""
    words: list[str] = []
    for line in graph.read_text(encoding="utf-8").splitlines():
        if not line.startswith("#") or not line.lstrip("# ").strip():
            if words:
                break
            continue
        words += line.lstrip("# ").split()
    text = " ".join(words)
    end = text.find(". ")
    text = text if end < 0 else text[: end + 1]
    return text if len(text) <= width else text[: max(0, width - 3)].rstrip() + "..."


def copy(dest: Path, force: bool) -> list[Path]:
    """Write every example file into ``dest/graphs``; refuses to overwrite one the user
    changed (``force``: does). A file already there as shipped is no conflict: the README's
    one-liner (``flowrt examples --copy . && flowrt run ...``) failed when run again."""
    files = shipped()
    if not files:
        raise FileNotFoundError("no example graphs in this installation of flowrt")
    folder = dest / "graphs"
    targets = [folder / f.name for f in files]
    existing = [t for f, t in zip(files, targets, strict=True) if t.exists() and not _same(f, t)]
    if existing and not force:
        raise FileExistsError(
            f"{existing[0]} exists and differs from the example ({len(existing)} of the "
            f"{len(targets)} files do): add --force to overwrite them"
        )
    folder.mkdir(parents=True, exist_ok=True)
    for f, target in zip(files, targets, strict=True):
        target.write_bytes(f.read_bytes())
    return targets


def _same(shipped_file: Any, target: Path) -> bool:
    try:
        return bool(target.is_file() and target.read_bytes() == shipped_file.read_bytes())
    except OSError:
        return False


def cmd_examples(args: argparse.Namespace) -> int:
    console = stdout_console()
    if args.copy is not None:
        dest = Path(args.copy)
        if dest.exists() and not dest.is_dir():  # (was "[Errno 20] Not a directory: ...")
            print(f"flowrt examples: --copy {args.copy}: not a folder", file=sys.stderr)
            return EXIT_BAD_GRAPH
        try:
            written = copy(dest, args.force)
        except OSError as e:  # exists, not writable, a file where the folder goes
            print(f"flowrt examples: {e}", file=sys.stderr)
            return EXIT_FAILED
        folder = written[0].parent
        if args.json:
            emit({"copied": [str(p) for p in written]})
        else:
            text = f"wrote {len(written)} files to {folder}: flowrt run {folder}/cambada.yaml"
            console.print(text, markup=False, highlight=False, soft_wrap=True)
        return EXIT_OK
    graphs = [f for f in shipped() if f.name.endswith(".yaml")]
    if args.json:
        emit([{"name": g.name, "summary": _summary(g, 400)} for g in graphs])
        return EXIT_OK
    width = max((len(g.name) for g in graphs), default=0)
    room = max(20, console.width - width - 3)
    for g in graphs:
        line = f"{g.name:<{width}}  {_summary(g, room)}"
        console.print(line, markup=False, highlight=False, soft_wrap=True)
    console.print("write them out: flowrt examples --copy .  (then flowrt run graphs/NAME)")
    return EXIT_OK


def add_parsers(sub: Any) -> None:
    p = sub.add_parser("examples", help="list the example graphs flowrt ships, or copy them out")
    p.add_argument("--copy", metavar="DIR", help="write them into DIR/graphs (as a clone has it)")
    p.add_argument("--force", action="store_true", help="with --copy: overwrite existing files")
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.set_defaults(func=cmd_examples)
