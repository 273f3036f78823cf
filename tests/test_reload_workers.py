"""``Runtime.reload`` (``flowrt ctl reload``) of a node whose module other nodes use too.

A node in a worker is reloaded in its worker only: the main process keeps the module's
classes, so the other nodes of the module (their output checks, their factories, the values
their workers send back) see nothing. An inline node's module is re-imported in the main
process; the other nodes of that module go on with the classes they had, which their
factories pickle and the type checks compare by name. Either way the params are carried to
the new class as they are, not validated again (a validator here multiplies by ten).

The node module is written into ``tmp_path`` and edited there, as a user edits a file.
"""

from __future__ import annotations

import importlib
import os
import pickle
import shutil
import signal
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import psutil
import pytest
from conftest import drained, wait_until

from flowrt import GraphBuilder, Runtime, SwapError, VirtualClock
from flowrt.node import NodeFactory

MODULE = textwrap.dedent(
    """
    from pydantic import BaseModel, field_validator

    from flowrt import Input, Node, Output

    VERSION = {version}


    class Offset(BaseModel):
        v: int = 0


    class Reading:
        '''A value of a class of this module: its readers check its type.'''

        def __init__(self, version, value):
            self.version = version
            self.value = value


    class Scale(Node):
        class Params(BaseModel):
            gain: int = 1
            offset: Offset = Offset()

            @field_validator("gain")
            @classmethod
            def _tenfold(cls, v):  # not idempotent: validated again, 2 would become 200
                return v * 10

        value = Input(int)
        out = Output(Reading)

        def process(self, value):
            return Reading(VERSION, value * self.params.gain + self.params.offset.v)


    class Version(Node):
        reading = Input(Reading)
        out = Output(int)

        def process(self, reading):
            return reading.version
    """
)
BROKEN = "\nclass Broken(:\n    pass\n"  # a syntax error at line 2 of what follows the module


class NodeModule:
    """The node module in ``tmp_path``, imported by name, edited in place."""

    def __init__(self, folder: Path, name: str) -> None:
        self.name = name
        self.path = folder / f"{name}.py"
        self.path.write_text(MODULE.format(version=1))

    def kind(self, cls: str) -> str:
        return f"{self.name}:{cls}"

    def edit(self, version: int, tail: str = "") -> None:
        """The file rewritten: an mtime of its own and no bytecode cache, so that an import
        sees the edit even within the second of the last (same size, same mtime)."""
        before = self.path.stat().st_mtime
        self.path.write_text(MODULE.format(version=version) + tail)
        os.utime(self.path, (before + 10, before + 10))
        shutil.rmtree(self.path.parent / "__pycache__", ignore_errors=True)

    @property
    def module(self) -> Any:
        return sys.modules[self.name]


@pytest.fixture
def mod(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[NodeModule]:
    monkeypatch.syspath_prepend(str(tmp_path))
    name = "reload_nodes_" + "".join(c if c.isalnum() else "_" for c in tmp_path.name)
    m = NodeModule(tmp_path, name)
    yield m
    sys.modules.pop(name, None)


def readings(values: list[Any]) -> list[tuple[int, int]]:
    return [(r.version, r.value) for r in values]


def versions_after(values: list[Any], n: int, version: int) -> bool:
    """At least ``n`` values and the last ``n`` all of ``version``."""
    return len(values) >= n and all(r.version == version for r in values[-n:])


# -- fast: no worker process -----------------------------------------------------------------


def test_a_factory_of_a_class_its_module_replaced_still_pickles(mod: NodeModule) -> None:
    """An inline node's reload re-imports the module in the main process: a factory made
    from the old class (another node of that module, restarted in a worker) must still
    pickle, and build the class its module has now, with the params as they were."""
    old = importlib.import_module(mod.name)
    params = old.Scale.Params(gain=2, offset={"v": 1})
    factory = NodeFactory(old.Scale, params, "b")
    mod.edit(2)
    new = importlib.reload(old)
    assert new.Scale is not factory.cls  # the old class is no longer the module's

    node = pickle.loads(pickle.dumps(factory))()  # as a worker unpickles and calls it

    assert type(node) is new.Scale
    assert type(node.params) is new.Scale.Params
    assert type(node.params.offset) is new.Offset
    assert node.params.gain == 20  # carried as it was, not validated again (200)
    assert node.params.model_fields_set == {"gain", "offset"}
    assert node.process(value=3).version == 2


def test_a_reload_factory_imports_anew_and_a_broken_edit_is_one_line(mod: NodeModule) -> None:
    """What a worker does for ``reload``: the module imported anew, the params carried to
    the edited class's; an edit that does not import is one ImportError line."""
    old = importlib.import_module(mod.name)
    factory = NodeFactory(old.Scale, old.Scale.Params(gain=2), "a")
    factory.reload = True
    mod.edit(2)
    node = pickle.loads(pickle.dumps(factory))()
    assert node.params.gain == 20
    assert type(node.params) is mod.module.Scale.Params
    assert node.process(value=1).value == 20
    assert node.process(value=1).version == 2

    mod.edit(3, BROKEN)
    with pytest.raises(ImportError) as info:
        pickle.loads(pickle.dumps(factory))()
    text = str(info.value)
    assert "\n" not in text
    assert "SyntaxError" in text
    assert f"{mod.path}, line" in text


@pytest.mark.parametrize(
    ("edit", "said"),
    [
        (("out = Output(Reading)", "result = Output(Reading)"), "outputs +result -out"),
        (("value = Input(int)", "value = Input(int)\n    extra = Input(int)"), "inputs +extra"),
    ],
)
def test_a_reload_in_a_worker_keeps_the_node_s_ports(
    mod: NodeModule, edit: tuple[str, str], said: str
) -> None:
    """An edit that changes the node's ports is refused in its worker, as an inline node's
    is by the swap's port check (the worker's reload said "reloaded", its result published
    on the old output, the new one never wired)."""
    old = importlib.import_module(mod.name)
    factory = NodeFactory(old.Scale, old.Scale.Params(gain=2), "a")
    factory.reload = True
    mod.edit(2)
    mod.path.write_text(mod.path.read_text().replace(*edit, 1))
    shutil.rmtree(mod.path.parent / "__pycache__", ignore_errors=True)
    with pytest.raises(ImportError) as info:
        pickle.loads(pickle.dumps(factory))()
    assert said in str(info.value)
    assert "a reload keeps a node's ports" in str(info.value)


async def test_inline_reload_leaves_the_module_s_other_nodes_running(mod: NodeModule) -> None:
    """Inline: ``a`` reloaded in the main process returns the edited code's values with its
    params carried over; ``b`` of the same class goes on with the old one, and ``c``, whose
    input is typed with the module's class, takes ``a``'s values of the new class (the old
    code failed ``a`` with "output 'out' expects Reading, got Reading")."""
    g = GraphBuilder("reload-inline")
    g.add("src", "counter", trigger={"timer": "10ms"}, params={"start": 1})
    g.add("a", mod.kind("Scale"), inputs={"value": "src.value"}, params={"gain": 2})
    g.add("b", mod.kind("Scale"), inputs={"value": "src.value"}, params={"gain": 3})
    g.add("c", mod.kind("Version"), inputs={"reading": "a.out"})
    clock = VirtualClock()
    async with Runtime(g.build(), clock=clock) as rt:
        a, b, c = (rt.subscribe(f"{n}.out", size=1024) for n in "abc")
        await clock.advance(0.1)
        before = readings(a.drain())
        b.drain()
        loaded = mod.module.Scale
        mod.edit(2)
        await rt.reload("a")
        await clock.advance(0.1)
        after, b_values, c_values = readings(a.drain()), readings(b.drain()), c.drain()
        params = rt.runner("a").rnode.params
        b_class = type(rt.runner("b").executor.node)  # type: ignore[attr-defined]
        stats = rt.stats()
    assert before
    assert all(v == 1 for v, _ in before)
    assert after
    assert all(v == 2 for v, _ in after)
    assert all(x % 20 == 0 for _, x in after)  # gain 20, not 200
    assert type(params) is mod.module.Scale.Params
    assert b_values  # b goes on, an instance of the old class (it reads the module's globals:
    assert b_class is loaded  # its values say version 2 too)
    assert c_values[-1] == 2
    for name in "abc":
        node = stats.node(name)
        assert (name, node.errors, node.restarts, node.state) == (name, 0, 0, node.state)
        assert node.state != "failed"


@pytest.mark.parametrize(
    "placement",
    ["inline", pytest.param("process", marks=[pytest.mark.slow, pytest.mark.subprocess])],
)
async def test_an_edit_that_does_not_import_leaves_the_old_instance(
    mod: NodeModule, placement: str
) -> None:
    """A syntax error in the edit: SwapError of one line, naming the file and line; the
    old instance runs on (the old code said nothing of the old instance, and in a worker
    gave the worker's traceback)."""
    g = GraphBuilder("reload-broken")
    g.add("src", "counter", trigger={"timer": "20ms"}, params={"start": 1})
    g.add("a", mod.kind("Scale"), inputs={"value": "src.value"}, placement=placement)
    async with Runtime(g.build()) as rt:
        out = rt.subscribe("a.out", size=1024)
        got: list[Any] = []
        assert await wait_until(lambda: drained(out, got))
        mod.edit(2, BROKEN)
        before = workers()
        for _ in range(3):
            with pytest.raises(SwapError) as info:
                await rt.reload("a")
        # each failed start's worker is stopped: none stays until the run's end
        assert await wait_until(lambda: workers() <= before)
        mark = len(drained(out, got))
        assert await wait_until(lambda: len(drained(out, got)) >= mark + 5)
        stats = rt.stats().node("a")
    text = str(info.value)
    assert "the old instance runs on" in text
    assert "SyntaxError" in text
    assert f"{mod.path}, line" in text
    assert "\n" not in text
    assert {r.version for r in got} == {1}
    assert stats.errors == 0
    assert stats.state != "failed"


def workers() -> set[int]:
    """This process's live children (worker processes, the forkserver)."""
    live = set()
    for c in psutil.Process().children(recursive=True):
        try:
            if c.status() != psutil.STATUS_ZOMBIE:
                live.add(c.pid)
        except psutil.NoSuchProcess:
            pass
    return live


# -- worker processes ------------------------------------------------------------------------


def kill_worker(rt: Runtime, node: str) -> None:
    pid = rt.runner(node).executor.pid  # type: ignore[attr-defined]
    assert pid is not None
    os.kill(pid, signal.SIGKILL)


@pytest.mark.slow
@pytest.mark.subprocess
@pytest.mark.parametrize("placement", ["process", "pool"])
async def test_worker_reload_runs_the_edit_there_only(mod: NodeModule, placement: str) -> None:
    """``a`` (process, or the only pool node of its module) reloaded: the edited code runs in
    its new worker with its params as they were; the main process does not re-import the
    module, so ``b`` (another worker of the same class) goes on without an error or a
    restart, and restarts later (its worker killed) with the edited file. The old code
    failed the reload ("Can't pickle <class 'Scale.Params'>") and then ``b``."""
    g = GraphBuilder("reload-worker")
    g.add("src", "counter", trigger={"timer": "20ms"}, params={"start": 1})
    g.add(
        "a",
        mod.kind("Scale"),
        inputs={"value": "src.value"},
        params={"gain": 2},
        placement=placement,
    )
    g.add("b", mod.kind("Scale"), inputs={"value": "src.value"}, placement="process")
    async with Runtime(g.build()) as rt:
        a, b = rt.subscribe("a.out", size=4096), rt.subscribe("b.out", size=4096)
        a_got: list[Any] = []
        b_got: list[Any] = []
        assert await wait_until(lambda: drained(a, a_got) and drained(b, b_got))
        loaded = mod.module.Scale
        mod.edit(2)
        await rt.reload("a")
        assert await wait_until(lambda: versions_after(drained(a, a_got), 5, 2))
        b_mark = len(drained(b, b_got))
        assert await wait_until(lambda: len(drained(b, b_got)) >= b_mark + 5)
        b_before_restart = rt.stats().node("b")
        kill_worker(rt, "b")
        assert await wait_until(lambda: versions_after(drained(b, b_got), 5, 2))
        stats = rt.stats()
        main_version, main_class = mod.module.VERSION, mod.module.Scale
    assert main_version == 1  # no re-import in the main process
    assert main_class is loaded
    new_a = [x for v, x in readings(a_got) if v == 2]
    assert all(x % 20 == 0 for x in new_a)  # gain 20 carried, not validated again (200)
    assert {r.version for r in b_got[:b_mark]} == {1}  # b's worker was not reloaded
    assert (b_before_restart.errors, b_before_restart.restarts) == (0, 0)
    assert stats.node("a").errors == 0
    assert stats.node("b").restarts == 1  # the kill, and its restart worked
    assert stats.node("b").state != "failed"


@pytest.mark.slow
@pytest.mark.subprocess
async def test_inline_reload_beside_a_worker_of_the_module(mod: NodeModule) -> None:
    """``a`` inline is reloaded in the main process; ``b`` of the same class in a worker goes
    on: its values, unpickled by name into the module's new classes, pass its output check
    and ``c``'s input check (both hold the old classes), and its restart pickles its old
    class by name. The old code failed ``b`` ("expects Reading, got Reading") and its
    restarts ("Can't pickle <class 'Scale'>")."""
    g = GraphBuilder("reload-inline-worker")
    g.add("src", "counter", trigger={"timer": "20ms"}, params={"start": 1})
    g.add("a", mod.kind("Scale"), inputs={"value": "src.value"}, params={"gain": 2})
    g.add("b", mod.kind("Scale"), inputs={"value": "src.value"}, placement="process")
    g.add("c", mod.kind("Version"), inputs={"reading": "b.out"})
    async with Runtime(g.build()) as rt:
        a, b, c = (rt.subscribe(f"{n}.out", size=4096) for n in "abc")
        a_got: list[Any] = []
        b_got: list[Any] = []
        c_got: list[Any] = []
        assert await wait_until(lambda: drained(b, b_got) and drained(c, c_got))
        mod.edit(2)
        await rt.reload("a")
        assert await wait_until(lambda: versions_after(drained(a, a_got), 5, 2))
        b_mark, c_mark = len(drained(b, b_got)), len(drained(c, c_got))
        assert await wait_until(lambda: len(drained(b, b_got)) >= b_mark + 5)
        assert await wait_until(lambda: len(drained(c, c_got)) >= c_mark + 5)
        b_before_restart = rt.stats().node("b")
        kill_worker(rt, "b")
        assert await wait_until(lambda: versions_after(drained(b, b_got), 5, 2))
        assert await wait_until(lambda: drained(c, c_got)[-1:] == [2])
        stats = rt.stats()
    assert all(x % 20 == 0 for v, x in readings(a_got) if v == 2)
    assert (b_before_restart.errors, b_before_restart.restarts) == (0, 0)
    assert stats.node("b").restarts == 1
    assert stats.node("b").state != "failed"
    assert stats.node("c").errors == 0  # b's values of the new class, typed with the old


@pytest.mark.slow
@pytest.mark.subprocess
async def test_pool_reload_is_refused_beside_another_pool_node_of_the_module(
    mod: NodeModule,
) -> None:
    """Two pool nodes of one module: re-importing it in a pool worker would replace the
    other's classes under it; refused, saying why and what to do, and ``a`` runs on."""
    g = GraphBuilder("reload-pool")
    g.add("src", "counter", trigger={"timer": "20ms"}, params={"start": 1})
    g.add("a", mod.kind("Scale"), inputs={"value": "src.value"}, placement="pool")
    g.add("b", mod.kind("Scale"), inputs={"value": "src.value"}, placement="pool")
    async with Runtime(g.build()) as rt:
        a = rt.subscribe("a.out", size=4096)
        got: list[Any] = []
        assert await wait_until(lambda: drained(a, got))
        mod.edit(2)
        with pytest.raises(SwapError) as info:
            await rt.reload("a")
        mark = len(drained(a, got))
        assert await wait_until(lambda: len(drained(a, got)) >= mark + 5)
        stats = rt.stats()
    text = str(info.value)
    assert f"b uses {mod.name} in the worker pool" in text
    assert "placement: process" in text
    assert {r.version for r in got} == {1}
    assert stats.node("a").errors == 0
    assert stats.node("b").errors == 0
