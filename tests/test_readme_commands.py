"""Every command of the README's command list runs, from the repository root and from another
folder (issue 38 item 10: ``flowrt replay recordings/rec_001 --graph graphs/cambada.yaml``
looked for the session beside the graph file).

The list is the ```bash block after "Other commands:" in README.md. A command runs as written
but for what a test cannot wait for or must not share: a run gets ``--duration``, fixed
ports become free ones, ``--measure 20s`` becomes 2 s, outputs go to a temporary folder;
``a|b`` alternatives run each. From another folder, the repository's paths (``graphs/``,
``nodes/``) are given relative to that folder, as a user there would type them, and what a
command writes (``recordings/``, ``stats.json``) lands in that folder. From the root, only the
commands that name a path run, and of the ``flowrt run`` variants only the first (the rest
read the same path): the other folder's run has them all, for the CI budget. A command added to the
list that this file does not know how to run fails the test: say here how to run it.
"""

from __future__ import annotations

import os
import re
import shlex
import socket
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"


def command_list(text: str) -> list[str]:
    """The commands (comments and continuation lines dropped) of the block after
    "Other commands:"."""
    head = text.index("Other commands:")
    start = text.index("```bash\n", head) + len("```bash\n")
    block = text[start : text.index("```", start)]
    out = []
    for line in block.splitlines():
        cmd = line.split("#", 1)[0].strip()
        if cmd:
            out.append(cmd)
    return out


def alternatives(cmd: str) -> list[str]:
    """``flowrt schema graph|stats`` -> both commands (the ``a|b`` word of a command)."""
    words = shlex.split(cmd)
    for i, w in enumerate(words):
        if "|" in w and not w.startswith(("{", "'")):
            return [shlex.join([*words[:i], alt, *words[i + 1 :]]) for alt in w.split("|")]
    return [cmd]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


# How each kind of command runs in a test (first match wins); a command none matches fails.
RUNS = "--duration 1 --no-ui --no-display"
KNOWN = [
    r"^flowrt (kinds|examples|validate|graph|schema|info|can analyse)\b",
    r"^flowrt (run|check|record|replay)\b",
    r"^flowrt ctl\b",
]


def adapt(cmd: str, where: Path, tmp: Path, control: int) -> list[str]:
    """The argv of ``cmd`` as run from ``where`` (see the module docstring)."""
    assert any(re.search(k, cmd) for k in KNOWN), f"README command not known here: {cmd}"
    words = shlex.split(cmd)
    if words[:2] == ["flowrt", "ctl"]:
        words[2:2] = ["--url", f"http://127.0.0.1:{control}"]
    out: list[str] = []
    i = 0
    while i < len(words):
        w = words[i]
        if w in ("--control", "--display-port"):
            out += [w, str(free_port())]
            i += 2
            continue
        if w == "--measure":
            out += [w, "2s"]
            i += 2
            continue
        if w == "--duration":
            out += [w, "1"]
            i += 2
            continue
        for folder in ("graphs/", "nodes/"):
            if w.startswith(folder) and where != ROOT:  # as a user in `where` types it
                w = os.path.relpath(ROOT / w, where)
        if where == ROOT and (w.startswith("recordings") or w in ("stats.json", "other.yaml")):
            w = str(tmp / w)  # the repository stays clean
        out.append(w)
        i += 1
    if out[1] in ("run", "record") or (out[1] == "replay" and "--duration" not in out):
        if "--duration" not in out:
            out += ["--duration", "1"]
        out += [a for a in ("--no-ui",) if a not in out]
        if "--no-display" not in out and "--display-port" not in out:
            out.append("--no-display")
    return [sys.executable, "-m", "flowrt.cli", *out[1:]]


def run_list(where: Path, tmp: Path) -> list[str]:
    """Run every command from ``where``; the failures, one line each."""
    env = {**os.environ, "COLUMNS": "200", "PYTHONPATH": str(ROOT)}
    other = tmp if where == ROOT else where  # "other.yaml": any graph of the user's
    (other / "other.yaml").write_text(
        "name: other\nnodes:\n  tick:\n    kind: counter\n    trigger: {timer: 100ms}\n"
    )
    control = free_port()
    commands = [c for line in command_list(README.read_text()) for c in alternatives(line)]
    if where == ROOT:  # the CI budget: what does not read a path runs once, from elsewhere
        runs = [c for c in commands if c.startswith("flowrt run")]
        paths = ("graphs/", "nodes/", "recordings", ".yaml", ".json")
        commands = [
            c
            for c in commands
            if c not in runs[1:] and not c.startswith("flowrt ctl") and any(x in c for x in paths)
        ]
    # Two lanes at once (the CI budget): the `ctl` commands, in order, against one running
    # graph, and every other command, in order (a recording is made before it is read).
    ctl = [c for c in commands if c.startswith("flowrt ctl")]
    rest = [c for c in commands if c not in ctl]
    failures: list[str] = []
    with ThreadPoolExecutor(1) as lane:
        others = lane.submit(_run_each, rest, where, tmp, control, env)
        failures += _ctl_lane(ctl, where, tmp, control, env)
        failures += others.result()
    return failures


def _ctl_lane(
    commands: list[str], where: Path, tmp: Path, control: int, env: dict[str, str]
) -> list[str]:
    """The ``flowrt ctl`` commands against cambada.yaml running with ``--control``."""
    if not commands:
        return []
    graph = adapt("flowrt run graphs/cambada.yaml", where, tmp, control)
    graph[graph.index("--duration") + 1] = "120"
    server = subprocess.Popen(
        [*graph, "--control", str(control)],
        cwd=where,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        _wait_for_control(control, 90)
        return _run_each(commands, where, tmp, control, env)
    finally:
        server.terminate()
        server.wait(30)


def _run_each(
    commands: list[str], where: Path, tmp: Path, control: int, env: dict[str, str]
) -> list[str]:
    """Run ``commands`` one after the other; the failures, one line each."""
    failures: list[str] = []
    for cmd in commands:
        argv = adapt(cmd, where, tmp, control)
        r = subprocess.run(argv, cwd=where, env=env, capture_output=True, text=True, timeout=120)
        if r.returncode and "(timed out)" in r.stderr:  # a loaded machine: once more
            r = subprocess.run(
                argv, cwd=where, env=env, capture_output=True, text=True, timeout=120
            )
        tail = (r.stderr.strip().splitlines() or [""])[-1]
        # `check` answers 1 when the timing is not shown to hold: a verdict, which on a
        # loaded machine may be either (README: "Exit 0 when ..., 1 when ...")
        ok = (0, 1) if argv[3] == "check" else (0,)
        # a timing change the admission test refuses is a verdict too (README: "refused
        # by admission control ... nothing was changed"): it rests on measured times
        if "refused by admission control" in r.stderr:
            ok = (1,)
        if r.returncode not in ok or "Traceback" in r.stderr:
            failures.append(f"{cmd!r} exited {r.returncode}: {tail}")
    return failures


def _wait_for_control(port: int, timeout: float) -> None:
    """Until the running graph answers ``GET /stats`` (its loop is up, not just its port)."""
    import urllib.request

    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/stats", timeout=10) as r:
                if r.status == 200:
                    return
        except OSError:
            pass
        time.sleep(0.5)
    raise AssertionError(f"the control endpoint on {port} did not answer")


def test_the_command_list_is_found_and_split() -> None:
    cmds = command_list(README.read_text())
    assert "flowrt replay recordings/rec_001 --graph graphs/cambada.yaml" in cmds
    assert alternatives("flowrt schema graph|stats") == [
        "flowrt schema graph",
        "flowrt schema stats",
    ]


@pytest.mark.subprocess
@pytest.mark.timeout(600)
@pytest.mark.parametrize("place", ["root", "elsewhere"])
def test_every_readme_command_runs(place: str, tmp_path: Path) -> None:
    where = ROOT if place == "root" else tmp_path / "elsewhere" / "deeper"
    where.mkdir(parents=True, exist_ok=True)
    failures = run_list(where, tmp_path)
    assert failures == [], "\n".join(failures)
