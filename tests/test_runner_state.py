"""One writer of a runner's state (issue 39): the moves its state may make, and no module but
``kernel/runner.py`` assigning a runner's fields (collaborators return decisions instead)."""

from __future__ import annotations

import ast
import itertools
import re
from pathlib import Path

import pytest

import flowrt
from flowrt.kernel.runner import NodeRunner, RunnerFields
from flowrt.kernel.state import MOVES, RunState, StateError
from flowrt.kernel.supervisor import GiveUp, Restart, Supervisor

S = RunState
# Written out here, apart from the kernel's table: a change to MOVES must change this too.
ALLOWED = {
    (S.starting, S.idle),  # set up
    (S.starting, S.backoff),  # its setup failed: restart
    (S.starting, S.failed),  # its setup failed: given up
    (S.idle, S.running),  # released
    (S.idle, S.starting),  # a swap in place: the old instance torn down first
    (S.idle, S.backoff),  # failed between calls (a worker lost under a pipelined call)
    (S.idle, S.failed),  # a teardown failed at the end
    (S.running, S.idle),  # returned
    (S.running, S.backoff),  # raised: restart
    (S.running, S.failed),  # raised: given up
    (S.backoff, S.idle),  # restarted, or a swap took over
    (S.backoff, S.failed),  # the restart's setup failed: given up
    (S.backoff, S.starting),  # a swap in place
    (S.failed, S.idle),  # a swap took over
    (S.failed, S.starting),  # a swap in place
}
MOVES_ALL = [(a, b) for a, b in itertools.product(S, S) if a is not b]


def _runner_in(state: RunState) -> RunnerFields:
    r = RunnerFields()
    r.name, r.state = "n", state
    return r


@pytest.mark.parametrize(("src", "dst"), [m for m in MOVES_ALL if m in ALLOWED])
def test_an_allowed_move_is_made(src: RunState, dst: RunState) -> None:
    r = _runner_in(src)
    r.move(dst)
    assert r.state is dst


@pytest.mark.parametrize(("src", "dst"), [m for m in MOVES_ALL if m not in ALLOWED])
def test_a_refused_move_raises_and_changes_nothing(src: RunState, dst: RunState) -> None:
    r = _runner_in(src)
    with pytest.raises(StateError, match=f"node n: no move from {src} to {dst}"):
        r.move(dst)
    assert r.state is src


@pytest.mark.parametrize("state", list(S))
def test_staying_is_not_a_move(state: RunState) -> None:
    r = _runner_in(state)
    r.move(state)
    assert r.state is state


def test_the_table_is_the_one_written_here() -> None:
    assert {(a, b) for a, dsts in MOVES.items() for b in dsts} == ALLOWED
    assert set(MOVES) == set(S)


# --- who assigns a runner's fields -----------------------------------------------------

ROOT = Path(flowrt.__file__).parent
RUNNER_PY = ROOT / "kernel" / "runner.py"
# How the kernel names a runner where it holds one (a collaborator's ``_r``, a scheduler's
# loop variable ``r``, a context's ``runner``): an assignment to a runner field through one
# of these, or through ``self`` in a runner class, is a write of the runner's state.
RUNNER_NAMES = {"r", "runner", "self._r", "self._runner", "rt.scheduler.runners"}


def _fields() -> set[str]:
    fields = set(RunnerFields.__annotations__)
    assert {"state", "executor", "rnode", "deferred", "task", "timer", "_busy"} <= fields
    return fields | {"busy"}


def _runner_classes(tree: ast.Module) -> set[str]:
    names = {"NodeRunner", "RunnerFields"}
    return names | {
        n.name
        for n in ast.walk(tree)
        if isinstance(n, ast.ClassDef)
        and any(ast.unparse(b).split(".")[-1] in names for b in n.bases)
    }


def writes_of_runner_fields(src: str, where: str) -> list[str]:
    """``file:line: target`` for each assignment of a runner's field in ``src``."""
    fields, tree = _fields(), ast.parse(src)
    runner_classes = _runner_classes(tree)
    found: list[str] = []

    def visit(node: ast.AST, in_runner: bool) -> None:
        for child in ast.iter_child_nodes(node):
            inside = in_runner or (isinstance(child, ast.ClassDef) and child.name in runner_classes)
            targets: list[ast.expr] = []
            if isinstance(child, ast.Assign):
                targets = list(child.targets)
            elif isinstance(child, ast.AugAssign | ast.AnnAssign):
                targets = [child.target]
            flat = [e for t in targets for e in (t.elts if isinstance(t, ast.Tuple) else [t])]
            for t in flat:
                if not isinstance(t, ast.Attribute) or t.attr not in fields:
                    continue
                base = ast.unparse(t.value)
                base = base.split("[")[0]  # rt.scheduler.runners[name] -> rt.scheduler.runners
                if base in RUNNER_NAMES or (base == "self" and inside):
                    found.append(f"{where}:{t.lineno}: {ast.unparse(t)}")
            visit(child, inside)

    visit(tree, False)
    return found


# A cheap first pass (parsing every module takes most of a second): a module is parsed
# when it names a runner class or assigns an attribute through a runner-like name.
_MAYBE = re.compile(r"NodeRunner|RunnerFields|(\br|runner|_r|\])\.\w+\s*(,|[-+]?=[^=])")


def test_only_the_runner_assigns_its_fields() -> None:
    nodes = ROOT.parent / "nodes"  # built-in nodes: the public API only, never a runner
    paths = [*ROOT.rglob("*.py"), *(nodes.rglob("*.py") if nodes.is_dir() else [])]
    sources = {p: p.read_text() for p in sorted(paths) if p != RUNNER_PY}
    writes = [
        w
        for path, src in sources.items()
        if _MAYBE.search(src)
        for w in writes_of_runner_fields(src, str(path.relative_to(ROOT.parent)))
    ]
    assert not writes, "runner fields assigned outside kernel/runner.py:\n" + "\n".join(writes)


def test_the_walk_sees_writes() -> None:
    """The walk finds what it must judge: the runner's own writes, and a collaborator's."""
    own = writes_of_runner_fields(RUNNER_PY.read_text(), "runner.py")
    assert any(w.endswith(": self.state") for w in own)
    assert any(w.endswith(": self.executor") for w in own)
    sample = (
        "class Supervisor:\n"
        "    def failed(self):\n"
        "        r = self._r\n"
        "        r.state, self._r.executor = 1, 2\n"
        "        self.state = 3\n"  # the supervisor's own field: not the runner's
        "class Precise(NodeRunner):\n"
        "    def f(self):\n"
        "        self._busy = True\n"
    )
    assert _MAYBE.search(sample)
    assert _MAYBE.search("    old, r.executor, r.rnode = r.executor, new, rnode\n")
    assert _MAYBE.search('    rt.scheduler.runners["a"].deferred = None\n')
    assert _MAYBE.search("    r._acts += 1\n")
    assert writes_of_runner_fields(sample, "x.py") == [
        "x.py:4: r.state",
        "x.py:4: self._r.executor",
        "x.py:8: self._busy",
    ]


# --- supervision decides, the runner applies ---------------------------------------------


def test_supervision_returns_a_decision_and_changes_nothing() -> None:
    """A failure gives ``Restart(backoff)`` while the policy allows, then ``GiveUp``,
    announced once the runner applied it; the supervisor never writes its runner (a
    read-only view here: a write would raise)."""
    from types import SimpleNamespace

    from flowrt.graph.spec import RestartPolicy
    from flowrt.kernel.counters import Counters

    class View:
        """Read-only: no setter, so an assignment by the supervisor raises."""

        def __init__(self) -> None:
            events: list[object] = []
            self._counts = Counters()
            spec = SimpleNamespace(restart=RestartPolicy(max_restarts=1, backoff=5))
            self._rnode = SimpleNamespace(spec=spec)
            clock = SimpleNamespace(now=lambda: 0.0)
            self._sched = SimpleNamespace(clock=clock, rel=lambda t: t, emit=events.append)
            self.events = events

        name = property(lambda self: "n")
        rnode = property(lambda self: self._rnode)
        counts = property(lambda self: self._counts)
        state = property(lambda self: RunState.running)
        stopping = property(lambda self: False)
        sched = property(lambda self: self._sched)

    view = View()
    sup = Supervisor(view)  # type: ignore[arg-type]
    first = sup.failed(ValueError("boom"))
    assert isinstance(first, Restart)
    assert first.backoff > 0
    view.counts.restarts += 1  # what the runner's restart counts
    second = sup.failed(ValueError("boom again"))
    assert isinstance(second, GiveUp)
    assert "boom again" in second.reason
    assert second.reason == sup.failed_reason
    sup.gave_up(second)  # what the runner calls once it is failed
    assert view.counts.errors == 2
    assert [type(e).__name__ for e in view.events] == ["NodeFailed", "NodeFailed", "NodeGaveUp"]


def test_node_runner_is_the_runner_fields_class() -> None:
    """The fields the walk checks are the ones NodeRunner has."""
    assert issubclass(NodeRunner, RunnerFields)
