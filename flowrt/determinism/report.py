"""What a deterministic replay found: the ``--json`` object, per-node lines, the divergence.

``--json`` prints exactly :meth:`ReplayReport.summary`: ``identical``, ``activations`` (re-
executed), ``compared`` (outputs whose digest was compared), ``first_divergence`` (``node``,
``port``, ``seq``, ``time`` in seconds since the run started, or null), ``wall_s`` and
``recorded_s``, and ``log_cut`` (why the log ends early, or null; then ``identical`` is false).
The per-node table and the values at the divergence are for people.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, Field

__all__ = ["Divergence", "NodeReplay", "ReplayReport", "report_lines", "verdict_line"]


class Divergence(BaseModel):
    """The first output that differs from the recording."""

    node: str
    port: str
    seq: int
    time: float = Field(description="seconds since the recorded run started (its activation)")
    why: str = Field(default="", description="digest differs, missing, extra, raised")
    recorded: str | None = Field(default=None, description="the recorded value, when recorded")
    replayed: str | None = Field(default=None, description="the re-executed value, if any")


class NodeReplay(BaseModel):
    """One node of the replayed graph: what was done with it."""

    node: str
    status: Literal["compared", "new", "not comparable", "source", "not run"]
    activations: int = 0
    compared: int = 0
    reason: str = ""


class ReplayReport(BaseModel):
    identical: bool
    activations: int
    compared: int
    first_divergence: Divergence | None
    wall_s: float
    recorded_s: float
    nodes: list[NodeReplay] = Field(default_factory=list)
    changes: list[str] = Field(default_factory=list, description="recorded changes, as applied")
    stopped_early: bool = Field(default=False, description="stopped at the first divergence")
    log_cut: str | None = Field(
        default=None,
        description="the log was not closed cleanly (a killed run, a full disk): what is wrong; "
        "only what was recorded before it was compared, so the replay is not 'identical'",
    )

    def summary(self) -> dict[str, Any]:
        """The ``--json`` object (its keys are the issue's, exactly)."""
        d = self.first_divergence
        return {
            "identical": self.identical,
            "activations": self.activations,
            "compared": self.compared,
            "first_divergence": None
            if d is None
            else {"node": d.node, "port": d.port, "seq": d.seq, "time": d.time},
            "wall_s": round(self.wall_s, 3),
            "recorded_s": round(self.recorded_s, 3),
            "log_cut": self.log_cut,
        }


def report_lines(report: ReplayReport) -> list[str]:
    """The report in words: one line per node, the changes, the verdict."""
    lines = []
    width = max((len(n.node) for n in report.nodes), default=4)
    for n in report.nodes:
        detail = f"{n.activations} activations, {n.compared} outputs compared"
        if report.stopped_early and n.status == "compared" and not n.activations:
            detail = "not reached: stopped at the first divergence"
        if n.status == "source":
            detail = "recorded values"
        elif n.status == "new":
            detail = f"{n.activations} activations on its trigger (not in the recording)"
        elif n.status in ("not comparable", "not run"):
            detail = n.reason
        elif n.reason:
            detail += f" ({n.reason})"
        lines.append(f"  {n.node:<{width}}  {n.status:<14}  {detail}")
    for c in report.changes:
        lines.append(f"  change: {c}")
    speed = report.recorded_s / report.wall_s if report.wall_s > 0 else 0.0
    lines.append(
        f"{report.activations} activations re-executed, {report.compared} outputs compared "
        f"in {report.wall_s:.2f} s ({report.recorded_s:.1f} s recorded, x{speed:.1f})"
    )
    lines.append(verdict_line(report))
    d = report.first_divergence
    if d is not None:
        if d.recorded is not None:
            lines.append(f"  recorded: {d.recorded}")
        if d.replayed is not None:
            lines.append(f"  replayed: {d.replayed}")
    return lines


def verdict_line(report: ReplayReport) -> str:
    """The report's verdict in one line (:func:`report_lines` gives it, then the values
    beside a divergence; ``--json``'s ``error`` message when it is not identical)."""
    d = report.first_divergence
    if d is not None:
        # seq: the port's publication number, not a value's own "seq" (a frame's)
        return (
            f"diverged at {d.node}.{d.port} seq {d.seq} (publication), t={d.time:.3f} s: {d.why}"
            + (" (stopped there)" if report.stopped_early else "")
        )
    if report.log_cut is not None:
        return (
            f"not identical: the log was cut ({report.log_cut}); {report.compared} outputs "
            f"compared over the {report.recorded_s:.1f} s recorded before the cut, what came "
            "after it was never checked"
        )
    if report.identical:
        return "identical: every compared output has its recorded digest"
    if any(n.status == "not comparable" for n in report.nodes):
        return "not identical: nothing could be compared (each node's reason above)"
    return (
        "not identical: nothing was compared: no node of this graph re-executes what the "
        "recording holds (was it recorded with this graph?)"
    )
