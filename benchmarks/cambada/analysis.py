"""From activation records to the paper's table rows: inter-activation, drops, misses.

Definitions (the same for the monolithic loop and flowrt, computed from the records the
trackers write in the process that runs them):

- window: per camera, frames ``k_lo .. k_hi`` where ``k_lo`` skips the first ``trim`` seconds
  (start-up) and ``k_hi`` is the last frame any tracker of that camera started, minus one
  (the run is cut at an arbitrary point);
- inter-activation: differences of consecutive start times of a task's activations on frames
  of the window (an activation skipped in between makes one long interval, as in the paper);
- drops: frames of the window on which the task was due (``k % period == phase``) but did not
  run (the monolithic loop skipped the frame, or flowrt skipped the release because the task's
  previous activation was still running);
- misses: activations that finished later than the task's deadline after the frame's release
  (its timestamp: the camera's nominal frame time for the monolithic loop, the capture node's
  publication for flowrt).

flowrt's own statistics (``--stats-json``) are reported beside them: its ``interval`` is
measured on the event loop when the activation is dispatched to the worker (not trimmed), and
its ``skipped`` and ``deadline_misses`` counters.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from .graph import Camera, Task


@dataclass
class Row:
    task: str
    period: int
    n: int = 0  # intervals
    max: float = math.nan  # ms
    min: float = math.nan
    mean: float = math.nan
    std: float = math.nan
    expected: int = 0
    drops: int = 0
    misses: int = 0
    activations: int = 0
    exec_max: float = math.nan  # ms, start to end in the worker / loop
    intervals: list[float] = field(default_factory=list, repr=False)  # ms, for histograms
    # flowrt's own statistics (dispatch side, whole run); None for the monolithic loop
    fl_std: float | None = None
    fl_max: float | None = None
    fl_min: float | None = None
    fl_mean: float | None = None
    fl_skipped: int | None = None
    fl_misses: int | None = None

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def load_records(record_dir: Path) -> dict[str, np.ndarray]:
    """node -> array of (seq, frame timestamp, start, end) rows, sorted by start."""
    out = {}
    for p in sorted(Path(record_dir).glob("*.json")):
        if p.name.endswith(".loop.json"):
            continue
        d = json.loads(p.read_text())
        r = np.asarray(d["records"], dtype=float).reshape(-1, 4)
        out[d["node"]] = r[np.argsort(r[:, 2])]
    return out


def rows(
    records: dict[str, np.ndarray],
    tasks: list[Task],
    cams: dict[str, Camera],
    trim: float,
    stats: dict[str, Any] | None = None,
    every_frame: bool = False,
) -> list[Row]:
    """One row per task; ``every_frame``: the tasks ran on every frame (period 1)."""
    fl = {n["name"]: n for n in stats["nodes"]} if stats else {}
    out = []
    for t in tasks:
        if every_frame:
            t = replace(t, period=1, phase=0)
        fps = float(cams[t.camera].params.get("fps", 20))
        k_lo = math.ceil(trim * fps)
        seen = [
            records[o.name][:, 0].max()
            for o in tasks
            if o.camera == t.camera and len(records.get(o.name, []))
        ]
        k_hi = int(max(seen)) - 1 if seen else -1
        r = records.get(t.name, np.empty((0, 4)))
        r = r[(r[:, 0] >= k_lo) & (r[:, 0] <= k_hi)]
        due = [k for k in range(k_lo, k_hi + 1) if k % t.period == t.phase]
        row = Row(t.name, t.period, expected=len(due), activations=len(r))
        row.drops = len(set(due) - set(r[:, 0].astype(int).tolist()))
        if len(r):
            row.exec_max = float((r[:, 3] - r[:, 2]).max() * 1000)
            if t.deadline_ms is not None:
                row.misses = int(((r[:, 3] - r[:, 1]) * 1000 > t.deadline_ms).sum())
        if len(r) > 1:
            iv = np.diff(r[:, 2]) * 1000
            row.n = len(iv)
            row.max, row.min, row.mean = float(iv.max()), float(iv.min()), float(iv.mean())
            row.std = float(iv.std(ddof=1)) if len(iv) > 1 else 0.0
            row.intervals = [round(float(x), 4) for x in iv]
        n = fl.get(t.name)
        if n is not None:
            iv = n["interval"]
            row.fl_std, row.fl_max, row.fl_min, row.fl_mean = (
                iv["std"],
                iv["max"],
                iv["min"],
                iv["mean"],
            )
            row.fl_skipped, row.fl_misses = n["skipped"], n["deadline_misses"]
        out.append(row)
    return out


def activation_series(
    records: dict[str, np.ndarray], node: str, origin: float
) -> tuple[np.ndarray, np.ndarray]:
    """(start time since ``origin`` in s, interval to the previous start in ms) of ``node``."""
    r = records.get(node)
    if r is None or len(r) < 2:
        return np.empty(0), np.empty(0)
    starts = r[:, 2]
    return starts[1:] - origin, np.diff(starts) * 1000
