"""How a capture node lives through a source that stalls or fails: alerts, backoff, reopens.

A camera that stops delivering is abandoned and reopened after an exponential backoff; a
file or image sequence that is only slow is reported, and reopened (at the frame it stalled
on) if it delivers nothing for ``open_timeout``. A failed open or read is retried with the
same backoff until ``max_retries`` consecutive failures, then the node gives up for good
(:class:`flowrt.FatalError`). Every problem is a :class:`flowrt.HealthAlert` and puts the
node in its error state; the next frame says ``source-recovered`` and leaves it.

The node owns the reader thread and drops it; :class:`SourceRecovery` owns the decisions and
the counters, so the policy reads in one place, apart from the frame path.
"""

from __future__ import annotations

import contextlib

from flowrt import FatalError, HealthAlert, NodeContext

from .params import CaptureParams
from .stderr import message_kind

__all__ = ["SourceRecovery"]

_NATIVE_KINDS_MAX = 256
"""Distinct kinds of native stderr line remembered; past it every line is logged at INFO."""


class SourceRecovery:
    """The failure state of one capture node's source, and what each event does to it.

    Invariants, between calls:

    - ``failures`` counts the failed opens and reads since the last frame; ``reopens`` all of
      them in the run, and ``last_error`` the latest reason (the teardown verdict quotes both).
    - ``backoff`` (seconds) is how long the next failure waits before its reopen:
      ``params.backoff`` after a frame, doubled by each failure up to ``max_backoff``.
      ``retry_at`` is when the pending reopen may happen.
    - ``troubled``: a problem was reported and no frame has flowed since, so the next frame
      announces ``source-recovered`` and clears the node's error state.
    - ``ended``: end of stream (``on_eof`` stop or exit) or retries exhausted; no reopen.
    - ``stalled``: a slow file or image read was reported, not (yet) counted as a failure.
    """

    def __init__(self, ctx: NodeContext, params: CaptureParams) -> None:
        self.ctx = ctx
        self.params = params
        self.camera = params.kind()[0] == "camera"
        self.failures = 0
        self.reopens = 0
        self.last_error = ""
        self.backoff = params.backoff / 1000
        self.retry_at = 0.0
        self.troubled = False
        self.ended = False
        self.stalled = False
        self.opened_at = 0.0
        self.last_frame_at = 0.0
        self._last_problem = ("", "")
        self._native_seen: set[str] = set()

    # -- reporting

    def alert(self, alert: str, detail: str, severity: str = "warning", note: str = "") -> None:
        """Emit a HealthAlert; log it too, unless it repeats the previous problem."""
        ctx = self.ctx
        t = ctx.elapsed()
        with contextlib.suppress(RuntimeError):  # emit() exists only on the event loop
            ctx.emit(HealthAlert(t, ctx.name, alert=alert, detail=detail + note, severity=severity))
        if (alert, detail) != self._last_problem or severity == "info":
            log = ctx.log.info if severity == "info" else ctx.log.warning
            log("%s: %s: %s%s", ctx.name, alert, detail, note)
        self._last_problem = (alert, detail)

    def native_log(self, lines: list[str]) -> None:
        """OpenCV's and FFmpeg's own messages: in this node's log, each kind once at INFO."""
        for line in lines:
            key = message_kind(line)
            first = key not in self._native_seen
            if first and len(self._native_seen) < _NATIVE_KINDS_MAX:
                self._native_seen.add(key)
            log = self.ctx.log.info if first else self.ctx.log.debug
            log("%s: opencv: %s", self.ctx.name, line)

    # -- events

    def opening(self) -> None:
        """A device is being opened: its first frame gets ``open_timeout`` from now."""
        self.opened_at = self.last_frame_at = self.ctx.now()
        self.stalled = False

    def failed(self, alert: str, detail: str) -> None:
        """Count and report a failed open or read, and schedule the reopen after the backoff.

        Raises :class:`flowrt.FatalError` once ``max_retries`` consecutive failures are
        exceeded: the node is failed for good (supervision decides what the run does)."""
        p = self.params
        self.troubled = True
        self.failures += 1
        self.reopens += 1
        self.last_error = detail
        if p.max_retries is not None and self.failures > p.max_retries:
            self.alert(alert, detail, "error")
            self.alert(
                "source-gave-up", f"{self.failures} consecutive failures; no more retries", "error"
            )
            self.ended = True
        else:
            self.alert(
                alert,
                detail,
                "error",
                f"; reopening in {self.backoff * 1000:.0f} ms (attempt {self.reopens + 1})",
            )
        with contextlib.suppress(RuntimeError):  # red in the table, with the reason
            self.ctx.set_error(detail)
        if self.ended:  # retries exhausted: the node is failed for good (supervision)
            raise FatalError(
                f"{p.source}: {self.failures} consecutive failures, max_retries "
                f"{p.max_retries} exhausted; last error: {detail}"
            )
        self.retry_at = self.ctx.now() + self.backoff
        self.backoff = min(self.backoff * 2, max(p.max_backoff, p.backoff) / 1000)

    def timed_out(self, first: bool, timeout: float, position: int) -> str | None:
        """No frame within the grab timeout: the failure to report (then reopen), or None.

        A camera that stalls is reopened at once. A file or image sequence that is slow
        (a huge frame, a network share) is reported and given until ``open_timeout`` before
        it is reopened, resuming at the frame it stalled on (``position``) rather than
        starting over.
        """
        p = self.params
        now = self.ctx.now()
        if first:
            if now - self.opened_at < p.open_timeout / 1000:
                return None  # still opening: no frame this time, not yet a failure
            return f"no first frame within {p.open_timeout:g} ms of opening {p.source}"
        if self.camera:
            return f"no frame from {p.source} within {timeout * 1000:g} ms"
        stalled = now - self.last_frame_at
        if stalled >= p.open_timeout / 1000:
            return (
                f"no frame from {p.source} for {stalled * 1000:.0f} ms; "
                f"resuming at frame {position}"
            )
        if not self.stalled:
            self.stalled = self.troubled = True
            self.alert(
                "grab-timeout", f"no frame from {p.source} within {timeout * 1000:g} ms; waiting"
            )
        return None

    def frame_read(self) -> None:
        """The device delivered a frame (it may still fail to convert)."""
        self.last_frame_at = self.ctx.now()
        self.stalled = False

    def frame_published(self, first: bool) -> None:
        """A frame is out: any problem is over, and the backoff starts afresh."""
        if self.troubled or first:  # (the first frame also clears an error left by a
            # previous instance: a swap or restart after "never delivered a frame")
            with contextlib.suppress(RuntimeError):
                self.ctx.clear_error()
        if self.troubled:
            self.troubled = False
            self.alert("source-recovered", f"{self.params.source}: frames flowing again", "info")
        self.failures = 0
        self.backoff = self.params.backoff / 1000

    def end_of_stream(self, frames: int) -> None:
        """The file or image sequence ended (``on_eof`` stop or exit): no reopen."""
        self.ended = True
        self.alert(
            "end-of-stream", f"{self.params.source}: end of stream after {frames} frames", "info"
        )

    def never_delivered(self) -> str:
        """The teardown verdict of a source that never delivered a frame."""
        why = (
            f" ({self.reopens} attempt{'' if self.reopens == 1 else 's'} failed; "
            f"last error: {self.last_error})"
            if self.reopens
            else ""
        )
        return f"{self.params.source}: never delivered a frame{why}"
