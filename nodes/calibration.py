"""The A/V calibration scene: an LED that flashes, seen by a camera that integrates light.

The acquisition system flowrt learns from measured its audio/video lag with an LED and a
speaker driven together. ``capture`` ``synthetic:flash`` is the camera half: the LED is on for
``flash_on`` every ``flash_period`` (on the runtime clock, from 0), and like a sensor that
integrates light over its exposure, a frame's LED brightness is the fraction of its exposure
interval ``[t, t + exposure)`` during which the LED was on, so that ``flowrt sync measure``
can place an onset between two frames: ``onset = t + exposure * (1 - brightness)`` for the
first lit frame. The ``audio`` node's ``synthetic:beep`` is the speaker half.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["FlashScene", "lit_fraction"]

DARK = 16  # the room's grey level
SPOT = 235  # the LED's, fully lit


def lit_fraction(t: float, exposure: float, on: float, period: float) -> float:
    """The share of ``[t, t + exposure)`` during which an LED on for ``[k*period,
    k*period + on)`` is lit."""
    if exposure <= 0:
        return 1.0 if (t % period) < on else 0.0
    total = 0.0
    k = math.floor((t - on) / period)
    while k * period < t + exposure:
        a, b = max(t, k * period), min(t + exposure, k * period + on)
        total += max(0.0, b - a)
        k += 1
    return min(1.0, total / exposure)


class FlashScene:
    """Frames of a dark room with an LED spot, lit by :func:`lit_fraction`."""

    def __init__(self, width: int, height: int, on: float, period: float) -> None:
        self.width, self.height = width, height
        self.on, self.period = on, period
        yy, xx = np.mgrid[0:height, 0:width]
        r = max(3, min(width, height) // 8)
        self.spot = (xx - width // 2) ** 2 + (yy - height // 2) ** 2 <= r * r

    def render_at(self, t: float, exposure: float) -> tuple[np.ndarray, float]:
        """(BGR image, LED brightness 0..1) of the exposure starting at ``t``."""
        b = lit_fraction(t, exposure, self.on, self.period)
        img = np.full((self.height, self.width, 3), DARK, np.uint8)
        img[self.spot] = round(DARK + (SPOT - DARK) * b)
        return img, b
