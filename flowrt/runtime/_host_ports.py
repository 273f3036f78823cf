"""The host program's own ports on a running graph: inject a value, subscribe to an output."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from ..edges import make_buffer
from ..graph.diagnostics import did_you_mean
from ..graph.spec import EdgePolicy
from ..kernel import NodeRunner, Scheduler
from ..kernel.outputs import OutputError
from ._subscription import Subscription


def runner_port(sched: Scheduler, target: str) -> tuple[NodeRunner, str]:
    """``node.port`` resolved, or KeyError naming the nearest names (TypeError: not text)."""
    if not isinstance(target, str):
        raise TypeError(f"a port is named 'node.port' (text), got {target!r}")
    node, _, port = target.partition(".")
    runner = sched.runners.get(node)
    if runner is None:
        raise KeyError(f"unknown node {node!r}" + did_you_mean(node, sched.runners))
    ports = [*runner.outputs, *runner.inputs, *runner.rnode.cls.inputs]
    if not port:  # a node's name alone ("src has no port ''")
        raise KeyError(f"{target!r}: name a port, node.port ({node}'s: {', '.join(ports)})")
    if port not in ports:
        raise KeyError(f"{node} has no port {port!r}" + did_you_mean(port, ports))
    return runner, port


def publish(sched: Scheduler, t: float, target: str, value: Any) -> None:
    """See :meth:`flowrt.Runtime.publish`."""
    runner, port = runner_port(sched, target)
    if port in runner.outputs:
        try:  # checked where it is made, as a node's own output (it failed at the reader)
            runner.out_check.value(port, value)
        except OutputError as e:
            raise TypeError(f"publish({target!r}): {e}") from None
        runner.publish(port, value, t)
    elif port in runner.inputs:
        runner.inputs[port].put(value, t)
    else:
        raise KeyError(f"{target} is an input that nothing feeds; connect it in the graph")


def subscribe(
    sched: Scheduler,
    now: Callable[[], float],
    target: str,
    policy: str,
    size: int,
    sampled: bool,
) -> Subscription:
    """See :meth:`flowrt.Runtime.subscribe`."""
    runner, port = runner_port(sched, target)
    if port not in runner.outputs:
        raise KeyError(f"{target} is not an output")
    if EdgePolicy(policy) is EdgePolicy.lossless:  # a host that stops reading would hold
        raise ValueError(  # the source back (a 10 ms counter ran 3 times in 0.5 s)
            f"subscribe({target!r}): policy 'lossless' would let this program stall the "
            "source; use 'queue' (dropped values counted) or 'latest'"
        )
    if isinstance(size, bool) or not isinstance(size, int) or size < 1:
        raise ValueError(f"subscribe({target!r}): size must be a whole number >= 1, not {size!r}")
    buf = make_buffer(policy, f"{target}->host", size, now)
    buf.sampled = sampled
    runner.outputs[port].append(buf)
    sched.buffers.append(buf)
    return Subscription(buf)
