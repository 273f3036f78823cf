"""How far apart two sensors' data are: the lag between the same events seen by each.

The calibration method of the in-vehicle acquisition system flowrt learns from (its chapter 7):
an LED and a speaker driven together, filmed and recorded; the lag is the time between the
LED's onset in the frames and the tone's onset in the audio (there: 20 to 127 ms, mean about
56 ms, audio late). Cameras are compared with each other the same way, onset against onset.

- Video onsets are found *between* frames: a sensor integrates light over its exposure, so the
  first lit frame's brightness b (0..1, normalised over the recording) says when in its
  exposure ``[t, t + E)`` the LED came on: ``t + E * (1 - b)``.
- Audio onsets are sample-exact: the first sample of each burst above a threshold of the peak.
- Each video onset is paired with the nearest onset of the other stream within half the
  events' spacing; the lag is other minus video (positive: the other stream is late).

Pure functions on arrays: the CLI (``flowrt sync measure``) reads the recording.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np

__all__ = ["LagReport", "audio_onsets", "measure_lag", "video_onsets"]


@dataclass(frozen=True)
class LagReport:
    """The lag of a stream against a reference, over the paired events (ms)."""

    lag_ms: float
    min_ms: float
    max_ms: float
    std_ms: float
    events: int
    lags_ms: tuple[float, ...] = ()  # per event, in time order
    times: tuple[float, ...] = ()  # the reference onsets (s)

    def json(self) -> dict[str, float | int]:
        d = asdict(self)
        del d["lags_ms"], d["times"]
        return d


def video_onsets(
    times: Sequence[float], brightness: Sequence[float], exposure: float, threshold: float = 0.05
) -> list[float]:
    """Onsets of a flashing light in frames stamped with their exposure's start ``times``."""
    b = np.asarray(brightness, dtype=float)
    t = np.asarray(times, dtype=float)
    if len(b) < 2:
        return []
    lo, hi = float(np.min(b)), float(np.max(b))
    if hi - lo <= 1e-9:
        return []
    n = (b - lo) / (hi - lo)
    onsets = []
    for k in range(1, len(n)):
        if n[k - 1] <= threshold < n[k]:
            onsets.append(float(t[k] + exposure * (1.0 - min(1.0, n[k]))))
    return onsets


def audio_onsets(
    times: np.ndarray, samples: np.ndarray, min_gap: float = 0.02, threshold: float = 0.1
) -> list[float]:
    """Sample times where a burst starts: above ``threshold`` of the peak after at least
    ``min_gap`` seconds below it."""
    x = np.abs(np.asarray(samples, dtype=float))
    if x.size == 0 or float(x.max()) <= 0:
        return []
    above = np.nonzero(x > threshold * float(x.max()))[0]
    if above.size == 0:
        return []
    t = np.asarray(times, dtype=float)[above]
    starts = [float(t[0])]
    gaps = np.nonzero(np.diff(t) > min_gap)[0]
    starts += [float(t[i + 1]) for i in gaps]
    return starts


def measure_lag(reference: Sequence[float], other: Sequence[float]) -> LagReport:
    """Pair each reference onset with the nearest other onset (within half the median spacing
    of the reference events) and summarise ``other - reference`` in ms."""
    ref = sorted(reference)
    oth = np.asarray(sorted(other), dtype=float)
    if not ref or oth.size == 0:
        return LagReport(math.nan, math.nan, math.nan, math.nan, 0)
    spacing = float(np.median(np.diff(ref))) if len(ref) > 1 else math.inf
    window = spacing / 2
    lags, when = [], []
    for r in ref:
        i = int(np.argmin(np.abs(oth - r)))
        d = float(oth[i] - r)
        if abs(d) < window:
            lags.append(d * 1000)
            when.append(r)
    if not lags:
        return LagReport(math.nan, math.nan, math.nan, math.nan, 0)
    a = np.asarray(lags)
    return LagReport(
        float(a.mean()),
        float(a.min()),
        float(a.max()),
        float(a.std()),
        len(lags),
        tuple(lags),
        tuple(when),
    )
