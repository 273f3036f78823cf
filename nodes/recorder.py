"""The ``recorder`` node: records its inputs, under any names, into an MCAP session.

    recorder:
      kind: recorder
      params: {path: recordings, name: drive}
      inputs:
        front_cam.frame: {from: front_cam.frame, policy: lossless, size: 16}
        ball.detection: {from: ball_fr.detection, policy: lossless}

Each input is a stream; its input name is the MCAP topic (``flowrt record`` names them after
their source, ``node.port``). Inputs should be ``lossless`` edges: the producer is never
dropped on, and since ``process`` only queues (frames by reference, holding their
shared-memory slot), the producer does not wait either unless the disk falls behind. Writing
happens in a process of its own (``writer: process``, the default:
:mod:`flowrt.recording.writer.channel`), which reads each frame from its shared-memory slot, so
neither the disk nor the writer's CPU work touches the event loop or its GIL; ``writer:
thread`` writes on threads of the runtime's process instead (:mod:`flowrt.recording.writer`).

A writer that cannot keep up loses messages *counted per stream*, and the node goes into the
error state at once (red in the status table until the next session) with one ``HealthAlert``
per burst of losses (a burst ends after ``BURST_QUIET`` s without one); a write error (disk full)
stops the recording, keeps the file, says why, and the graph goes on. When a recording stops
its per-stream table is logged and saved as ``streams.json`` in the session.

A detection stream (a tracker's output: centroid, bbox and the ``source``/``timestamp`` of
its frame) whose camera is recorded too is also written as ``foxglove.ImageAnnotations`` on
``CAMERA/annotations/DETECTIONS`` (``cam.frame/annotations/ball.detection``), stamped with
its frame's time, so Foxglove's image panel draws the detections on the frames
(``annotations: false`` turns it off).

With ``split_size`` (``4GiB``) and/or ``split_duration`` (``10m``) a session holds several
files, ``NAME_NNN_000.mcap``, ``NAME_NNN_001.mcap`` ..., each a complete, standalone MCAP
(:mod:`flowrt.recording.split`); the per-stream table counts across all of them.

With ``profile: ros2`` (``flowrt record --profile ros2``) the session is a rosbag2 folder:
CDR messages under ``ros2msg`` schemas (:mod:`flowrt.recording.ros2_profile`) and, once the
files are finished, ``metadata.yaml``; ROS 2 tools open it as a bag.

With ``deterministic: true`` (``flowrt record --deterministic``) the session also holds what a
deterministic replay needs (:mod:`flowrt.determinism`): every activation of the processing
nodes with the sequence numbers of its inputs, a digest of each of their outputs, and the
sources' values with their exact times. The recorder then takes every value it records as it
is published (through the scheduler's observer), not from its input edges: each value's
place in its stream is known, so replay finds it again. One deterministic recorder per graph
(the scheduler has one observer).

At run time ``flowrt ctl record start|stop`` (RTDB record ``flowrt.record.NODE``) starts a new
session or closes the current one; the command may also be ``{"action": "start", "name":
"drive"}`` (the live view's record panel): the new session is then ``drive_NNN``; a start
without a name is ``NAME_NNN``, the ``name`` param's. The node says where its sessions go in
``flowrt.recordings.NODE`` (the folder), so the live view can list them for review.

A swap (``flowrt ctl swap rec recorder --params '{"compression": "zstd"}'``) while recording
goes on in a new session (``drive_001`` then ``drive_002``: the new params make a new file):
the new instance obeys the last start or stop command in its ``setup``, beside the old one,
so its session is open when it takes over, and each value is in one of the two sessions;
the statistics' ``reports`` list both sessions' tables.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import errno
import math
import os
import time
from collections import deque
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

from flowrt import AudioBlock, Frame, Input, InputTrigger, Node
from flowrt.determinism.log import METADATA
from flowrt.determinism.observer import Observer
from flowrt.node import SEED_ENV
from flowrt.recording import (
    ProcessRecordingWriter,
    RecordingWriter,
    SplitPolicy,
    Writer,
    build_report,
    new_session,
    nominal_rates,
)
from flowrt.recording.encoding import Overlay, annotations_topic, is_detection
from flowrt.recording.report import RecordingReport, report_text
from flowrt.recording.rosbag2 import write_metadata
from flowrt.recording.session import (
    SESSION_FILE,
    SESSION_NAME,
    mcap_files,
    session_metadata,
    timing_json,
)
from flowrt.recording.streams import is_set, split_set
from flowrt.rtdb import RECORD_COMMAND as COMMAND_RECORD
from flowrt.rtdb import RECORDING_FOLDER as FOLDER_RECORD
from flowrt.rtdb import RECORDING_SESSION as STATUS_RECORD

from .recorder_params import RecorderParams

FINISH_WAIT = 1.0
"""Seconds a stop waits for the file to be finished before leaving it to the writer thread."""
LET_GO_WAIT = 2.0
"""Seconds a stop waits for the writer to let go of the frames' slots (a process: a round trip)."""
AnyWriter = Writer  # either writer: the recorder never asks which
LAGS_KEPT = 8
"""The last values of a stream stamped ahead of its releases its lead is taken from."""
BURST_QUIET = 1.0
"""Seconds without a new loss that end a burst of losses: the next loss is alerted again."""


class StampLags:
    """One session's streams stamped ahead of their publication (audio), and by how much.

    An audio block is stamped at its first sample and published at the audio node's first
    activation after it is complete: one block late or two by the activations' lateness
    against the first one's, often alternately, so the last block's lag alone may be the
    short one and the report takes the largest of the last few as the stream's lead
    (build_report's ``leads``). The last few only: a late activation at the start (set-up, a
    first pause) would otherwise end the stream's window early by its delay, hiding a loss.
    """

    def __init__(self) -> None:
        self._lags: dict[str, deque[float]] = {}  # topic -> the last LAGS_KEPT lags, seconds

    def submit(
        self, writer: AnyWriter, topic: str, value: Any, t: float, seq: int, now: float
    ) -> bool:
        """``writer.submit``, noting how long after its stamp ``t`` an audio block was
        published (``now``: the recorder is handed each value's publication time)."""
        if isinstance(value, AudioBlock):
            self._lags.setdefault(topic, deque(maxlen=LAGS_KEPT)).append(now - t)
        return writer.submit(topic, value, t, seq)

    def leads(self) -> dict[str, float]:
        """Topic -> the lead of each stream stamped ahead of its releases."""
        return {topic: max(lags) for topic, lags in self._lags.items() if lags}


class LossAlerts:
    """One session's losses and write error in the node's state: red, and one alert a burst.

    A writer that is behind refuses values one at a time as its bound frees and fills
    again; an alert per new count (``recorder behind: 1 lost`` ... ``15 lost``) flooded the
    event ring with what the per-stream counters (``streams.json``, ``flowrt info``) already
    hold. So the node's error reason changes (a ``HealthAlert``) when a burst begins, and
    a burst ends after ``BURST_QUIET`` s without a new loss, not at the next accepted
    value (as :class:`flowrt.refusals.Refusals` does): a writer behind accepts one between
    two refusals. The node stays red until a new session.
    """

    def __init__(self) -> None:
        self._lost = 0  # lost_behind of the session when last looked at
        self._last = -math.inf  # runtime time of the last new loss
        self._said_error = False

    def watch(self, ctx: Any, writer: AnyWriter) -> None:
        if writer.error is not None:
            if not self._said_error:
                self._said_error = True
                ctx.log.error("%s: recording stopped: %s", ctx.name, writer.error)
                ctx.set_error(f"recording stopped: {writer.error}")
            return
        lost = sum(s.lost_behind for s in writer.streams.values())
        if lost <= self._lost:
            return
        now = ctx.now()
        begins = now - self._last >= BURST_QUIET
        self._lost, self._last = lost, now
        if begins:
            worst = max(writer.streams.values(), key=lambda s: s.lost_behind)
            ctx.set_error(
                f"recorder behind: {lost} lost ({worst.topic}: {worst.lost_behind}) as a "
                "burst of losses began; every loss is counted per stream"
            )


class Recorder(Node):
    """Records every input into ``path/NAME_NNN/NAME_NNN.mcap`` (or its parts); see above."""

    # what a swap over the control endpoint may change (flowrt kinds shows it)
    swappable = frozenset(
        {
            "name",
            "session",
            "images",
            "compression",
            "chunk_size",
            "flush_interval",
            "max_frames",
            "crc",
            "split_size",
            "split_duration",
            "annotations",
            "log_report",
        }
    )
    swap_folders = {"session": "path"}  # a session only inside its recordings folder

    Params = RecorderParams

    any_inputs = Input(
        object, required=False, policy="lossless", doc="any stream, under its topic name"
    )
    inline_only = True

    @classmethod
    def default_trigger(cls, params: Any) -> InputTrigger:
        return InputTrigger()

    async def setup(self) -> None:
        self._loop = asyncio.get_running_loop()
        self.writer: AnyWriter | None = None
        self.session: Path | None = None
        self.sessions: list[Path] = []
        self.reports: list[RecordingReport] = []
        self._started_at = 0.0
        self._started_wall = 0.0
        self._seq: dict[str, int] = {}
        self._sources: dict[str, str] = {}
        self._cameras: dict[str, str] = {}  # frame source node -> its recorded topic
        self._losses = LossAlerts()
        self._next_command_check = 0.0
        self._draining: AnyWriter | None = None  # closing: its frames still come back
        self._task: asyncio.Task[None] | None = None  # a start/stop asked for by ctl
        self._indexes: dict[str, int] = {}  # messages accepted per topic (the current file set)
        self._log_seq: dict[str, int] = {}
        self._observer: Observer | None = None
        if self.params.deterministic:
            self._observer = Observer(self, self.ctx.name)
            self.ctx.observe(self._observer)  # from now on: before any source publishes
        start, prefix, seq = _standing_command(self.ctx, self.params)
        self._rtdb_ok, self._command_seq = seq is not None, seq or 0
        if not start:  # else said once open (meanwhile the swapped-out instance's, if any)
            self._publish_status("")
        if self._rtdb_ok:
            self.ctx.rtdb.write(FOLDER_RECORD + self.ctx.name, str(Path(self.params.path)))
        if start:
            await asyncio.to_thread(self._open, self._stats(), prefix)
            self._publish_status(str(self.session))

    # --- sessions ---------------------------------------------------------------------------

    def _open(self, stats: Any, prefix: str) -> None:
        """Create the session folder ``prefix_NNN`` and the file (on a thread: it touches
        the disk).

        ``stats`` is taken on the loop before: the runtime's tables are not read from here.
        """
        p = self.params
        session = Path(p.session) if p.session and not self.sessions else None
        try:
            made = session is None or not session.exists()
            if session is not None:
                session.mkdir(parents=True, exist_ok=True)
            else:
                session = new_session(p.path, prefix)
        except OSError as e:
            raise _cannot_start(e, session or Path(p.path)) from None
        try:
            _open_cleanly(session, made, lambda: self._open_in(session, stats))
        except OSError as e:
            raise _cannot_start(e, session) from None

    def _open_in(self, session: Path, stats: Any) -> None:
        p = self.params
        self._started_wall = time.time()
        self._started_at = self.ctx.now()
        options: dict[str, Any] = {
            "image_formats": dict(p.images),
            "epoch_offset": self._started_wall - self._started_at,
            "chunk_size": p.chunk_size,
            "compression": p.compression,
            "flush_interval": p.flush_interval,
            "max_frames": p.max_frames,
            "crc": p.crc,
            "direct_io": p.direct_io,
            "on_written": self._written,
            "split": SplitPolicy(p.split_size, p.split_duration),
            "profile": p.profile,
        }
        path = session / f"{session.name}.mcap"
        writer: AnyWriter
        if p.writer == "process":
            options["priority"] = p.writer_priority
            writer = ProcessRecordingWriter(path, loop=self._loop, **options)
        else:
            writer = RecordingWriter(path, **options)
        attachments = [("timing.json", "application/json", timing_json(stats))]
        if p.graph_file:
            try:
                text = Path(p.graph_file).read_bytes()
                attachments.insert(0, ("graph.yaml", "application/yaml", text))
            except OSError as e:
                self.ctx.log.warning("%s: graph file not attached: %s", self.ctx.name, e)
        graph = getattr(stats, "graph", "") if stats is not None else ""
        metadata = session_metadata(graph, self._started_wall)
        observer = self._observer
        if observer is not None:
            metadata[METADATA] = observer.metadata(os.environ.get(SEED_ENV, "0"))
            if not p.graph_file and observer.graph is not None:
                try:  # the graph is part of what makes the run reproducible
                    text = Path(observer.graph.file).read_bytes()
                    attachments.insert(0, ("graph.yaml", "application/yaml", text))
                except OSError:
                    self.ctx.log.info("%s: no graph file to attach", self.ctx.name)
        self._indexes, self._log_seq, self._lags = {}, {}, StampLags()
        writer.open(metadata, attachments)
        self.writer, self.session = writer, session
        self.sessions.append(session)
        self._losses = LossAlerts()
        pid = getattr(writer, "pid", None)
        where = f" (writer process {pid})" if pid is not None else ""
        self.ctx.log.info("%s: recording into %s%s", self.ctx.name, writer.path, where)

    async def _close(self) -> None:
        """Stop recording: the file is finished on the writer thread, whatever the loop does.

        The teardown of a node is bounded (the runtime then frees the frame pools), and a slow
        disk may need longer: so the queued frames are first copied off the pool, the report
        is written by the writer thread once the file is complete, and the thread keeps the
        process alive until then.
        """
        writer, session = self.writer, self.session
        if writer is None or session is None:
            return
        self.writer, self._draining = None, writer
        started = self._started_at
        duration = self.ctx.now() - started
        start = dt.datetime.fromtimestamp(self._started_wall, dt.UTC).isoformat()
        stats = self._stats()
        # the session's start on the statistics' clock (seconds since the runtime's start)
        since = None if stats is None else stats.uptime - duration
        rates = nominal_rates(stats, since) if stats is not None else {}
        leads = self._lags.leads()

        def report() -> RecordingReport:
            return build_report(writer, session.name, start, duration, rates, started, leads)

        def attachments() -> list[tuple[str, str, bytes]]:
            return [("streams.json", "application/json", report().model_dump_json().encode())]

        writer.request_close(attachments, partial(self._finished, session, report))
        for frame in writer.detach_frames():
            frame.release()
        for _ in range(round(LET_GO_WAIT / 0.005)):  # the frame being encoded now, if any
            if not writer.encoding_frame():
                break
            await asyncio.sleep(0.005)
        self._release_done()
        if not await asyncio.to_thread(writer.join, FINISH_WAIT):
            self.ctx.log.info(
                "%s: %s: the disk is behind, finishing the file in the background",
                self.ctx.name,
                writer.path,
            )
        self._release_done()
        self._draining = None

    def _finished(self, session: Path, report_of: Any) -> None:
        """On the writer thread, the file complete: save and say the per-stream table."""
        report: RecordingReport = report_of()
        if self.params.profile == "ros2":  # the folder becomes a rosbag2 bag
            try:
                write_metadata(session, mcap_files(session))
            except (OSError, ValueError) as e:
                report.error = report.error or f"metadata.yaml not written: {e}"
        try:
            (session / SESSION_FILE).write_text(report.model_dump_json(indent=1))
        except OSError as e:
            with contextlib.suppress(OSError):  # half a report reads as damage: none says
                (session / SESSION_FILE).unlink(missing_ok=True)  # "did not finish", as it is
            self.ctx.log.error("%s: %s not saved: %s", self.ctx.name, SESSION_FILE, _oserror(e))
        self.reports.append(report)
        if report.lost or report.error:
            text = report_text(report) if self.params.log_report else ""
            self.ctx.log.warning(
                "%s: recording %s stopped with %d lost\n%s",
                self.ctx.name,
                session,
                report.lost,
                text,
            )
        elif self.params.log_report:
            self.ctx.log.info("%s: recording stopped\n%s", self.ctx.name, report_text(report))

    def get_state(self) -> Any:
        """The sessions and their tables, for the instance a swap puts in this one's place:
        without them the tables of the sessions before a swap were gone from ``stats.json``.
        The list itself: this session's table is added once its file is finished, after."""
        return {"recorder_sessions": self.sessions, "recorder_reports": self.reports}

    def set_state(self, state: Any) -> None:
        if isinstance(state, dict) and "recorder_reports" in state:
            self.sessions[:0] = state["recorder_sessions"]
            state["recorder_reports"].extend(self.reports)
            self.reports = state["recorder_reports"]

    def report(self) -> Any:
        """The per-stream table of every recording this node made (in ``stats.json``)."""
        if not self.reports:
            return None
        return [r.model_dump(mode="json") for r in self.reports]

    def _stats(self) -> Any:
        try:
            return self.ctx.stats()
        except RuntimeError:
            return None

    # --- the hot path -----------------------------------------------------------------------

    def process(self, **inputs: Any) -> None:
        now = self.ctx.now()
        if now >= self._next_command_check:
            self._next_command_check = now + 0.1
            self._check_command()
        writer = self.writer
        if writer is None:
            return
        if self._observer is None:  # deterministic: the observer hands them over (value())
            for topic, value in inputs.items():
                if value is not None:  # a value without a stamp: when it was published
                    t = self.ctx.input_time(topic) or now  # (a loaded recorder runs late)
                    self._record(writer, topic, self._source_of(topic), value, t, False)
            if self.params.annotations:  # after the frames: their cameras are known then
                for topic, value in inputs.items():
                    if value is not None and not isinstance(value, Frame) and is_detection(value):
                        self._overlay(writer, topic, value)
        self._losses.watch(self.ctx, writer)

    def _record(
        self,
        writer: AnyWriter,
        topic: str,
        source: str,
        value: Any,
        now: float,
        overlay: bool = True,
    ) -> bool:
        """Queue one value for the writer (and its annotations); False when refused."""
        if is_set(value):  # a sync set: each frame a stream of its own, then the index
            value, members = split_set(topic, value)
            for sub, member in members:
                self._record(writer, sub, f"{source}/{sub.rpartition('/')[2]}", member, now)
        if topic not in writer.streams:
            writer.declare(topic, source)
        is_frame = isinstance(value, Frame)
        if is_frame:
            t, seq = value.timestamp, value.seq
            value.acquire()  # the writer's link, given back in _release_done
        else:
            stamp = getattr(value, "timestamp", None)
            t = stamp if isinstance(stamp, float) and stamp > 0 else now
            s = getattr(value, "seq", None)
            seq = s if isinstance(s, int) and s >= 0 else self._seq.get(topic, 0)
            self._seq[topic] = seq + 1
        accepted = self._lags.submit(writer, topic, value, t, seq, now)
        if not accepted and is_frame:
            value.release()
        if is_frame:
            self._cameras.setdefault(value.source, topic)
        elif overlay and self.params.annotations and is_detection(value):
            self._overlay(writer, topic, value)
        return accepted

    # --- the deterministic log (flowrt.determinism.observer.Sink) ---------------------------

    @property
    def recording(self) -> bool:
        return self.writer is not None

    def log(self, topic: str, record: dict[str, Any], t: float) -> None:
        writer = self.writer
        if writer is not None:
            if topic not in writer.streams:  # events, not a periodic stream: no gaps
                writer.declare(topic, self.ctx.name, irregular="true")
            seq = self._log_seq[topic] = self._log_seq.get(topic, -1) + 1
            writer.submit(topic, record, t, seq)

    def value(self, topic: str, source: str, value: Any) -> int | None:
        """A value the observer saw published: recorded, and its index in ``topic``."""
        writer = self.writer
        if writer is None or not self._record(writer, topic, source, value, self.ctx.now()):
            return None
        index = self._indexes.get(topic, 0)
        self._indexes[topic] = index + 1
        return index

    def _overlay(self, writer: AnyWriter, topic: str, det: Any) -> None:
        """The detection again, as annotations on its camera's image (when that is recorded)."""
        camera = self._cameras.get(det.source)
        if camera is None or self.params.profile == "ros2":
            return
        name = annotations_topic(camera, topic)
        if name not in writer.streams:
            writer.declare(name, self._source_of(topic), annotates=camera)
        seq = det.seq if isinstance(getattr(det, "seq", None), int) and det.seq >= 0 else 0
        writer.submit(name, Overlay(det), det.timestamp, seq)

    def _written(self) -> None:
        """From the writer (any thread): give the written frames' links back on the loop."""
        if not self._loop.is_closed():
            self._loop.call_soon_threadsafe(self._release_done)

    def _release_done(self) -> None:
        for writer in (self.writer, self._draining):
            while writer is not None and writer.done:
                writer.done.popleft().release()

    def _source_of(self, topic: str) -> str:
        """The ``node.port`` feeding an input, from the runtime's edge table."""
        if not self._sources:
            stats = self._stats()
            for e in getattr(stats, "edges", []) if stats is not None else []:
                src, _, dst = e.name.partition("->")
                node, _, port = dst.partition(".")
                if node == self.ctx.name:
                    self._sources[port] = src
        return self._sources.get(topic, topic)

    # --- control ----------------------------------------------------------------------------

    def _check_command(self) -> None:
        if not self._rtdb_ok:
            return
        try:
            rec = self.ctx.rtdb.read(COMMAND_RECORD + self.ctx.name)
        except Exception:
            self._rtdb_ok = False
            return
        if rec is None or rec.seq == self._command_seq:
            return
        if self._task is not None and not self._task.done():
            return  # a start or stop is under way: the command is read again after it
        self._command_seq = rec.seq
        cmd, prefix = _command(rec.value, self.params.name)
        if cmd == "start" and self.writer is None:
            self._task = self._loop.create_task(self._start_async(prefix))
        elif cmd == "stop" and self.writer is not None:
            self._task = self._loop.create_task(self._stop_async())

    async def _start_async(self, prefix: str) -> None:
        try:
            await asyncio.to_thread(self._open, self._stats(), prefix)
        except OSError as e:
            self.ctx.set_error(f"cannot start recording: {e}")
            return
        self.ctx.clear_error()  # a new session: what the previous one lost is in its report
        self._publish_status(str(self.session))

    async def _stop_async(self) -> None:
        await self._close()
        self._publish_status("")

    def _publish_status(self, session: str) -> None:
        try:
            self.ctx.rtdb.write(STATUS_RECORD + self.ctx.name, session)
        except Exception:  # outside a runtime (tests): no RTDB, nothing to publish
            self._rtdb_ok = False

    async def teardown(self) -> None:
        task = getattr(self, "_task", None)
        if task is not None and not task.done():  # a session being opened is closed too
            with contextlib.suppress(Exception):
                await task
        writer = getattr(self, "writer", None)
        if writer is not None:
            await self._close()


class NoSpace(OSError):
    """The disk is full: a recording cannot start (or go on) until space is freed, so a
    restart cannot help (``fatal``: the recorder is given up with this one line, no
    traceback; a second recording into the same full disk says the same, not the
    ``FileExistsError`` of a half-made file)."""

    fatal = True

    def __str__(self) -> str:
        return str(self.args[0])


_FULL = {errno.ENOSPC, errno.EDQUOT}


def _standing_command(ctx: Any, p: RecorderParams) -> tuple[bool, str, int | None]:
    """Whether a recorder records from its ``setup`` on, the prefix of that session, and the
    sequence number of the command it thereby obeys (0: none; None: no RTDB).

    The last ``start``/``stop`` command outlives the instance that obeyed it: an instance
    swapped in (or restarted) obeys it in ``setup``, before it takes over, so its session is
    open for the first value the old one did not take. Obeyed at the first activation
    instead, it lost the values taken while its writer opened (2-4 of a 20 Hz counter per
    ``ctl swap``, in neither session and counted nowhere). Without a command: ``start``.
    """
    try:
        rec = ctx.rtdb.read(COMMAND_RECORD + ctx.name)
    except Exception:  # outside a runtime (tests): no RTDB, no command
        return p.start, p.name, None
    if rec is None:
        return p.start, p.name, 0
    action, prefix = _command(rec.value, p.name)
    if action not in ("start", "stop"):
        return p.start, prefix, rec.seq
    return action == "start", prefix, rec.seq


def _command(value: Any, name: str) -> tuple[Any, str]:
    """A command record's action and the prefix of the session a start makes: the name the
    command gives (``{"action": "start", "name": "drive"}``: the live view's), else the
    recorder's own ``name``. Per command: a name given once was kept for every later start,
    and ``flowrt ctl record start`` recorded into the page's ``drive_002``."""
    if not isinstance(value, dict):
        return value, name
    given = value.get("name")
    action = value.get("action")
    if action == "start" and isinstance(given, str) and SESSION_NAME.match(given):
        return action, given
    return action, name


def _oserror(e: OSError) -> str:
    """An OSError in words, ENOSPC named: ``rec_001.mcap: no space left on device (ENOSPC)``."""
    if e.errno in _FULL:
        where = f"{e.filename}: " if e.filename else ""
        return f"{where}no space left on device ({errno.errorcode[e.errno]})"
    return str(e)


def _open_cleanly(session: Path, made: bool, open_in: Callable[[], None]) -> None:
    """Open a session; when that fails nothing half-made is left (a retry starts clean), but
    a recording that was there before is never removed (a session named again, by a swap:
    it deleted a finished 28 MB recording)."""
    mcap = session / f"{session.name}.mcap"
    existed = mcap.exists()
    try:
        open_in()
    except OSError:
        with contextlib.suppress(OSError):
            if not existed:
                mcap.unlink(missing_ok=True)
            if made and not any(session.iterdir()):
                session.rmdir()
        raise


def _cannot_start(e: OSError, where: Path) -> OSError:
    if e.errno in _FULL or isinstance(e, NoSpace):
        return NoSpace(f"cannot record into {where}: no space left on device (the disk is full)")
    return e
