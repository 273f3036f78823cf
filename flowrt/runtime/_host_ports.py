"""The host program's own ports on a running graph: inject a value, subscribe to an output."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from ..edges import make_buffer
from ..graph.diagnostics import did_you_mean
from ..graph.spec import EdgePolicy
from ..kernel import NodeRunner, Scheduler
from ._subscription import Subscription


def runner_port(sched: Scheduler, target: str) -> tuple[NodeRunner, str]:
    """``node.port`` resolved, or KeyError naming the nearest names."""
    node, _, port = target.partition(".")
    runner = sched.runners.get(node)
    if runner is None:
        raise KeyError(f"unknown node {node!r}" + did_you_mean(node, sched.runners))
    ports = [*runner.outputs, *runner.inputs, *runner.rnode.cls.inputs]
    if port not in ports:
        raise KeyError(f"{node} has no port {port!r}" + did_you_mean(port, ports))
    return runner, port


def publish(sched: Scheduler, t: float, target: str, value: Any) -> None:
    """See :meth:`flowrt.Runtime.publish`."""
    runner, port = runner_port(sched, target)
    if port in runner.outputs:
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
    EdgePolicy(policy)
    buf = make_buffer(policy, f"{target}->host", size, now)
    buf.sampled = sampled
    runner.outputs[port].append(buf)
    sched.buffers.append(buf)
    return Subscription(buf)
