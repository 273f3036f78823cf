"""Supervision: when a failed node is started again, when it is given up, and what is logged.

One rule for every node and placement (the scheduler's restart path applies it):

- A failure is an exception from ``setup`` or ``process``, a watchdog expiry, or a worker
  process that died. The node is restarted (a fresh instance and a fresh ``setup``) after a
  back-off that doubles with each *consecutive* failure, from ``restart.backoff`` up to
  ``restart.max_backoff``; the exponent is capped, so the back-off of the millionth failure
  is as well defined as that of the tenth.
- A node is *given up* (state ``failed``, a :class:`~flowrt.events.NodeGaveUp` event, the
  reason in its statistics) when it fails ``restart.max_failures`` times in a row without a
  completed activation in between (a crash loop, at start-up or later), when it has been
  restarted ``restart.max_restarts`` times in all, when the policy is ``never``, or at once
  when the error says restarting cannot help (``error.fatal`` is true, e.g. a worker that
  cannot import the node's script).
- A failure for want of operating-system resources (out of file descriptors, processes or
  memory: EMFILE, ENFILE, EAGAIN, ENOMEM), e.g. a worker that cannot be started while a
  flood of clients holds the descriptors, says nothing about the node: it is retried with
  the same back-off but never counts towards ``max_failures``, so the node comes back by
  itself once the resources do.
- Logging never floods: the first failure of each kind (exception type and message) is
  logged with its full traceback; repeats of a kind already logged are counted and summed
  up at most once per :data:`SUMMARY_INTERVAL` ("ball_fr: 412 more failures of the same
  kind in the last 10 s"), and once more when the node is given up or stopped.
"""

from __future__ import annotations

import errno
import logging
import re
from dataclasses import dataclass

from .graph.spec import RestartPolicy

log = logging.getLogger("flowrt.scheduler")

SUMMARY_INTERVAL = 10.0  # seconds between two summaries of repeated failures of one node
MAX_EXPONENT = 30  # 2**30 x the back-off is far beyond any max_backoff: the cap never binds
MAX_KINDS = 16  # distinct failure kinds logged in full per node; later new kinds are counted


def backoff_s(policy: RestartPolicy, consecutive: int) -> float:
    """Seconds to wait before restart number ``consecutive`` (1 for the first failure).

    ``backoff * 2 ** (consecutive - 1)``, capped at ``max_backoff``; the exponent is capped
    too, so a node failing for days never overflows a float.
    """
    exponent = min(max(consecutive - 1, 0), MAX_EXPONENT)
    return min(policy.backoff * 2.0**exponent, policy.max_backoff) / 1000


def give_up_reason(
    policy: RestartPolicy,
    consecutive: int,
    restarts: int,
    fatal: bool,
    never_started: bool = False,
) -> str | None:
    """Why the node must not be restarted again, or None to restart it.

    ``never_started``: the failure was at start-up (set-up, a worker importing the node's
    module) and the node has never completed an activation.
    """
    if fatal:
        return "restarting cannot help"
    if policy.policy == "never":
        return "restart policy never"
    if policy.max_failures is not None and consecutive >= policy.max_failures:
        return f"{consecutive} consecutive failures without a completed activation"
    if policy.max_restarts is not None and restarts >= policy.max_restarts:
        return f"max_restarts {policy.max_restarts} reached"
    limit = policy.max_start_failures
    if never_started and limit is not None and consecutive >= limit:
        return f"{consecutive} consecutive failures at start-up: it never started"
    return None


RESOURCE_ERRNOS = frozenset({errno.EMFILE, errno.ENFILE, errno.EAGAIN, errno.ENOMEM})


def out_of_resources(exc: BaseException | None) -> bool:
    """Did ``exc`` (or what caused it) come from the operating system running out of
    descriptors, processes or memory? Such a failure is the machine's, not the node's."""
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, OSError) and exc.errno in RESOURCE_ERRNOS:
            return True
        exc = exc.__cause__ or exc.__context__
    return False


def failure_kind(error: str) -> str:
    """The first line of ``Type: message``: what a summary or a give-up reason shows."""
    return error.strip().splitlines()[0][:1000] if error.strip() else "?"


_NUMBER = re.compile(r"\d+")


def _same_kind_key(error: str) -> str:
    """Two failures are "the same kind" when they differ only in numbers (an index, a frame
    count, a pid), so that a message that counts does not defeat the rate limit."""
    return _NUMBER.sub("#", failure_kind(error))


@dataclass
class _Repeats:
    count: int = 0
    since: float = 0.0


class FailureLog:
    """Rate-limited logging of one node's failures (see the module documentation)."""

    def __init__(self, node: str) -> None:
        self.node = node
        self._seen: dict[str, str] = {}  # kind key -> the first such error, as shown
        self._pending: dict[str, _Repeats] = {}
        self._window_start: float | None = None

    def failed(self, now: float, error: str, traceback: str) -> None:
        """Log a failure in full if its kind is new, else count it for the next summary."""
        key = _same_kind_key(error)
        if key not in self._seen and len(self._seen) < MAX_KINDS:
            self._seen[key] = failure_kind(error)
            if traceback.strip():
                log.error("node %s failed: %s\n%s", self.node, error, traceback.rstrip())
            else:
                log.error("node %s failed: %s", self.node, error)
            return
        if self._window_start is None:
            self._window_start = now
        rep = self._pending.setdefault(key, _Repeats(since=now))
        rep.count += 1
        if now - self._window_start >= SUMMARY_INTERVAL:
            self.flush(now)

    def flush(self, now: float) -> None:
        """Log one summary line per kind counted since the last summary."""
        if self._window_start is None:
            return
        span = max(now - self._window_start, 0.0)
        for key, rep in self._pending.items():
            log.error(
                "%s: %d more failure%s of the same kind in the last %.0f s (%s)",
                self.node,
                rep.count,
                "" if rep.count == 1 else "s",
                max(span, 1.0),
                self._seen.get(key, key),
            )
        self._pending.clear()
        self._window_start = None
