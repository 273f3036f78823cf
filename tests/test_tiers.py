"""The tier machinery itself (tests/tiers.py): what it derives from a test's code, and the
guard's verdicts. A broken reader would leave every test in the fast tier."""

from __future__ import annotations

import asyncio
import subprocess
import sys

import tiers


@tiers.uses("browser")
def _drives_a_browser() -> None:
    pass


def _runs_a_program() -> None:
    subprocess.run([sys.executable, "-c", "pass"], check=True)


def _calls_a_helper() -> None:
    _runs_a_program()


async def _asyncio_program() -> None:
    await asyncio.create_subprocess_exec("true")


def _imports_in_the_function() -> None:
    import subprocess as sp

    sp.run(["true"], check=False)


def _names_a_worker_but_runs_nothing() -> dict[str, str]:
    return {"placement": "process"}


def _runs_a_graph_with_a_worker() -> None:
    from flowrt import Runtime

    Runtime({"placement": "process"})  # type: ignore[arg-type]


def _plain() -> int:
    return sum(range(10))


# Reached through a dict: a test naming the helpers directly would itself be tiered by them.
H = {
    f.__name__: f
    for f in (
        _drives_a_browser,
        _runs_a_program,
        _calls_a_helper,
        _asyncio_program,
        _imports_in_the_function,
        _names_a_worker_but_runs_nothing,
        _runs_a_graph_with_a_worker,
        _plain,
    )
}
CLUES = {tiers._NAMES_A_PROCESS, tiers._RUNS}


def tiers_of(name: str) -> set[str]:
    return tiers.tiers_used(H[name]) - CLUES


def test_what_starts_a_process_is_read_from_the_code_transitively() -> None:
    assert tiers_of("_runs_a_program") == {"subprocess"}
    assert tiers_of("_calls_a_helper") == {"subprocess"}
    assert tiers_of("_asyncio_program") == {"subprocess"}
    assert tiers_of("_imports_in_the_function") == {"subprocess"}
    assert tiers_of("_drives_a_browser") == {"browser"}
    assert tiers_of("_plain") == set()


def test_a_placement_counts_only_in_a_graph_that_runs() -> None:
    assert tiers.tiers_used(H["_names_a_worker_but_runs_nothing"]) == {tiers._NAMES_A_PROCESS}
    assert tiers.tiers_used(H["_runs_a_graph_with_a_worker"]) >= CLUES


def test_these_tests_stay_in_the_fast_tier() -> None:
    """The helpers above are reached through ``H``: reading this file's tests finds nothing."""
    assert tiers.tiers_used(test_what_starts_a_process_is_read_from_the_code_transitively) == set()


def test_the_guard_hears_of_a_process_started_during_a_test() -> None:
    tiers.install_guard()
    saved = tiers._started
    tiers._started = []
    try:
        tiers._note("a program (x)")
        assert tiers._started == ["a program (x)"]
    finally:
        tiers._started = saved
    popen = vars(sys.modules["subprocess"])["Popen"]  # (not by name: it would tier this test)
    assert getattr(popen._execute_child, "__flowrt_guard__", False)


def test_the_wall_limit_grows_with_the_load_never_below_three_times() -> None:
    assert tiers._wall_limit() >= 3 * tiers.FAST_SECONDS
