"""An audio source: a microphone, a WAV file, or a synthetic tone or beep.

::

    mic:
      kind: audio
      params: {source: "synthetic:beep", rate: 48000, channels: 1, block: 1024,
               beep_period: 1s, beep_on: 100ms, offset: 40ms}

Sources:

- ``device:NAME`` (or ``device:`` for the default input): a microphone through
  ``sounddevice``/PortAudio (optional: ``pip install sounddevice``). Blocks the device lost
  (PortAudio's input overflow) are counted as ``lost`` with their reason.
- ``file:PATH.wav``: 16-bit PCM WAV, resampled to nothing (``rate`` and ``channels`` come from
  the file), paced in real time, ``on_eof: stop|loop``.
- ``synthetic:tone``: a continuous sine at ``tone_hz``.
- ``synthetic:beep``: the A/V calibration source of the acquisition system flowrt learns
  from (an LED and a speaker driven together): a ``tone_hz`` burst of ``beep_on`` every
  ``beep_period``, late by ``offset`` (plus, with ``jitter``, a random 0..jitter per beep,
  seeded) against the flashes of a ``capture`` ``synthetic:flash`` source of the same run:
  both follow the runtime clock, so the lag ``flowrt sync measure`` finds has a known truth.

Output ``audio``: :class:`flowrt.AudioBlock` of ``block`` samples per channel, the first
sample's time on the runtime clock (sample ``i`` at ``timestamp + i / rate``), in sequence.
A synthetic or file source never skips a block: an activation that comes late publishes
every block that is due.
"""

from __future__ import annotations

import math
import queue
import wave
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator

from flowrt import AudioBlock, Node, Output, TimerTrigger, parse_duration_ms, resolve_path
from flowrt.files import file_problem

__all__ = ["Audio", "AudioParams", "beep_starts"]


def _seconds(v: Any) -> float:
    ms = parse_duration_ms(v)
    if ms < 0 or ms > 3_600_000:
        raise ValueError("must be a duration between 0 and 1 h, e.g. 100ms")
    return ms / 1000


class AudioParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    source: str = Field(
        default="synthetic:tone",
        description="device:NAME | file:PATH.wav | synthetic:tone | synthetic:beep",
    )
    rate: int = Field(default=48000, ge=1000, le=384_000, description="samples per second")
    channels: int = Field(default=1, ge=1, le=64)
    block: int = Field(default=1024, ge=16, le=1 << 20, description="samples per message")
    tone_hz: float = Field(default=1000.0, gt=0, le=20_000, allow_inf_nan=False)
    amplitude: float = Field(default=0.5, ge=0, le=1, allow_inf_nan=False)
    beep_on: float = Field(default=0.1, description="beep length (duration, e.g. 100ms)")
    beep_period: float = Field(default=1.0, description="time between beeps (duration)")
    offset: float = Field(default=0.0, description="beeps late by this against the flashes")
    jitter: float = Field(default=0.0, description="each beep later by a random 0..jitter")
    seed: int = Field(default=0, ge=0)
    on_eof: Literal["stop", "loop"] = "stop"

    @field_validator("beep_on", "beep_period", "offset", "jitter", mode="before")
    @classmethod
    def _durations(cls, v: Any) -> float:
        return _seconds(v)

    @field_validator("source")
    @classmethod
    def _source(cls, v: str, info: ValidationInfo) -> str:
        kind, _, rest = v.partition(":")
        if kind == "synthetic" and rest in ("tone", "beep"):
            return v
        if kind == "device":
            return v
        if kind == "file" and rest:
            path = resolve_path(rest, info)
            problem = file_problem(path)
            if problem is not None:
                raise ValueError(f"audio file: {problem}")
            return f"file:{path}"
        raise ValueError("source must be device:NAME, file:PATH.wav, synthetic:tone or :beep")


def beep_starts(t0: float, t1: float, p: AudioParams) -> list[float]:
    """Start times of the beeps that overlap [t0, t1): ``k * period + offset + jitter_k``."""
    period = p.beep_period
    first = math.floor((t0 - p.offset - p.jitter - p.beep_on) / period)
    last = math.floor((t1 - p.offset) / period)
    out = []
    for k in range(first, last + 1):
        extra = 0.0
        if p.jitter:
            extra = float(np.random.default_rng([p.seed, k & 0xFFFFFFFF]).uniform(0, p.jitter))
        out.append(k * period + p.offset + extra)
    return out


class Audio(Node):
    """Audio blocks from a device, a WAV file or a synthetic source (see the module doc)."""

    # what a swap over the control endpoint may change (flowrt kinds shows it)
    swappable = frozenset({"tone_hz", "amplitude", "beep_on", "beep_period", "offset", "jitter"})

    Params = AudioParams
    audio = Output(AudioBlock, doc="blocks of samples, the first sample's time stamped")

    @classmethod
    def default_trigger(cls, params: Any) -> TimerTrigger:
        rate = params.rate
        if params.source.startswith("file:"):
            rate = _wav_rate(params.source[5:]) or rate
        return TimerTrigger(timer=1000.0 * params.block / rate)

    def setup(self) -> None:
        p = self.params
        self.kind, _, self.target = p.source.partition(":")
        self.rate, self.channels = p.rate, p.channels
        self.seq = 0
        self.t0: float | None = None  # the first sample's time
        self.lost = 0  # blocks the device lost (input overflow)
        self.ended = False
        self._wave: Any = None
        self._stream: Any = None
        self._queue: queue.Queue[tuple[np.ndarray, float, bool]] = queue.Queue(maxsize=256)
        if self.kind == "file":
            self._wave = wave.open(self.target)  # noqa: SIM115  (closed in teardown)
            if self._wave.getsampwidth() != 2:
                raise ValueError(f"{self.target}: only 16-bit PCM WAV files are read")
            self.rate, self.channels = self._wave.getframerate(), self._wave.getnchannels()
        elif self.kind == "device":
            self._open_device()

    def teardown(self) -> None:
        if self._wave is not None:
            self._wave.close()
        if self._stream is not None:
            self._stream.stop()
            self._stream.close()

    def process(self) -> None:
        now = self.ctx.now()
        if self.kind == "device":
            self._drain_device()
            return
        if self.t0 is None:
            self.t0 = now
        block_s = self.params.block / self.rate
        while not self.ended and self.t0 + (self.seq + 1) * block_s <= now + 1e-9:
            samples = self._synthetic() if self.kind == "synthetic" else self._from_file()
            if samples is None:
                return
            self._publish(samples, self.t0 + self.seq * block_s)

    def report(self) -> dict[str, Any]:
        """What the statistics show of the source (``reports``)."""
        return {"blocks": self.seq, "rate": self.rate, "channels": self.channels,
                "lost": self.lost}  # fmt: skip

    # --- sources ----------------------------------------------------------------------------

    def _publish(self, samples: np.ndarray, t: float) -> None:
        block = AudioBlock(samples, self.rate, t, self.seq, self.ctx.name)
        self.seq += 1
        self.ctx.publish("audio", block)

    def _synthetic(self) -> np.ndarray:
        p = self.params
        assert self.t0 is not None
        n = p.block
        times = self.t0 + (self.seq * n + np.arange(n)) / self.rate
        wave_ = p.amplitude * np.sin(2 * np.pi * p.tone_hz * times)
        if self.target == "beep":
            on = np.zeros(n, dtype=bool)
            for start in beep_starts(float(times[0]), float(times[-1]) + 1 / self.rate, p):
                on |= (times >= start) & (times < start + p.beep_on)
            wave_ = np.where(on, wave_, 0.0)
        return np.repeat(wave_.astype(np.float32)[:, None], self.channels, axis=1)

    def _from_file(self) -> np.ndarray | None:
        raw = self._wave.readframes(self.params.block)
        got = len(raw) // (2 * self.channels)
        if got < self.params.block and self.params.on_eof == "loop":
            self._wave.rewind()
            raw += self._wave.readframes(self.params.block - got)
            got = len(raw) // (2 * self.channels)
        if got == 0:
            self.ended = True
            self.ctx.request_stop()  # on_eof: stop (a loop never gets here)
            return None
        pcm = np.frombuffer(raw[: got * 2 * self.channels], dtype="<i2")
        return (pcm.reshape(got, self.channels).astype(np.float32) / 32768.0).copy()

    # --- a microphone -----------------------------------------------------------------------

    def _open_device(self) -> None:
        try:
            import sounddevice as sd
        except ImportError:
            self.ctx.set_error("audio device: needs sounddevice (pip install sounddevice)")
            return
        name = self.target or None

        def callback(data: np.ndarray, frames: int, time_info: Any, status: Any) -> None:
            overflow = bool(getattr(status, "input_overflow", False))
            try:
                self._queue.put_nowait((data.copy(), frames / self.rate, overflow))
            except queue.Full:
                self.lost += 1  # the loop took nothing for a long time: counted

        try:
            self._stream = sd.InputStream(
                device=name, channels=self.channels, samplerate=self.rate,
                blocksize=self.params.block, dtype="float32", callback=callback,
            )  # fmt: skip
            self._stream.start()
        except Exception as e:  # no such device, busy: an error state, not a crash loop
            self.ctx.set_error(f"audio device {name or 'default'}: {e}")

    def _drain_device(self) -> None:
        now = self.ctx.now()
        while True:
            try:
                data, dur, overflow = self._queue.get_nowait()
            except queue.Empty:
                return
            if overflow:
                self.lost += 1  # PortAudio dropped input before this block: one lost block
            self._publish(data, now - dur)


def _wav_rate(path: str) -> int | None:
    """A WAV file's sample rate, or None when it cannot be read (set-up says why)."""
    try:
        with wave.open(path) as w:
            return int(w.getframerate())
    except (OSError, EOFError, wave.Error):
        return None
