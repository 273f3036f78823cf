"""Audio as a stream of blocks: what an ``audio`` node publishes and a recorder writes.

A block is a few milliseconds of samples (frames x channels) with the time of its *first*
sample on the runtime clock, its sample rate and a sequence number. The time of sample ``i``
is ``timestamp + i / rate``: sample-exact, which is what aligning audio with video needs
(the acquisition system flowrt learns from measured its audio 20-127 ms late against video).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["AudioBlock"]


@dataclass(frozen=True)
class AudioBlock:
    """``samples``: float32 in [-1, 1] or int16, shape (frames, channels)."""

    samples: np.ndarray
    rate: int  # samples per second, per channel
    timestamp: float  # runtime clock, seconds: the first sample's time
    seq: int  # blocks since the source started: a gap is a lost block
    source: str = ""

    @property
    def frames(self) -> int:
        return int(self.samples.shape[0])

    @property
    def channels(self) -> int:
        return int(self.samples.shape[1]) if self.samples.ndim == 2 else 1

    @property
    def duration(self) -> float:
        return self.frames / self.rate

    def pcm16(self) -> bytes:
        """Interleaved little-endian signed 16-bit samples (foxglove.RawAudio's pcm-s16)."""
        s = self.samples
        if s.dtype != np.int16:
            s = (np.clip(s, -1.0, 1.0) * 32767).astype("<i2")
        return np.ascontiguousarray(s).astype("<i2").tobytes()
