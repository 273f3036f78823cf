"""Tracker: CAMBADA colour-based detection of one object per node, on the frames of a capture.

Each ``tracker`` node follows one object (``object`` param: a name from
:data:`flowrt.nodes.colour.OBJECTS` — ``ball``, ``blue_goal``, ``yellow_goal``, ``blue_post``,
``yellow_post``, ``obstacle``, ``line``, ``candle`` — or a custom spec) with the paper's
windowed search (:class:`flowrt.nodes.colour.ObjectTracker`): it starts where the object was
last seen, so the search cost stays small while the object is tracked. The last known position
is node state, kept between activations (and lost on a restart, like any node state).

Output ``detection``: a :class:`FrameDetection` — the colour module's ``Detection`` (found,
centroid, bbox, area, confidence, cost = pixels classified, object) plus the ``source``,
``seq``, ``timestamp`` and ``size`` of the frame it was computed on, so that a display can draw
it on the right frame.

Params
------
``object``
    Name of the tracked object: a key of ``OBJECTS``, or any name when ``spec`` is complete.
``spec``
    A full :class:`~flowrt.nodes.colour.ObjectSpec` (``colour``, ``kind``, ``min_area``...), or
    only some of its fields to override those of the named object (e.g. ``{roi: [0, .5, 1, 1]}``).
``colours``
    Custom colour classes in ``space``: ``name: [[lo, hi], [lo, hi], [lo, hi]]`` (H in degrees,
    S and V 0..255 for hsv; Y, M, P for ymp; lo > hi wraps a hue/phase range). They take
    precedence over the predefined classes of the same name.
``space``
    ``hsv`` (default) or ``ymp`` (the paper's luma/modulus/phase space).
``bins``
    Quantisation of the lookup table per BGR channel (16..256).

Bad input never becomes a traceback: an unknown object or colour, or a custom colour class
that matches no colour at all, is a located error when the graph loads; a frame that is not
colour (GRAY) gives a ``bad-input`` health event (inline) or log message (worker), and a
not-found detection.
"""

from __future__ import annotations

import contextlib
import difflib
from dataclasses import dataclass, fields
from typing import Any, Literal

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator, model_validator

from flowrt import Frame, HealthAlert, Input, Node, Output

from .colour import (
    EXTRA_CLASSES,
    OBJECTS,
    ColourClass,
    ColourTable,
    Detection,
    ObjectSpec,
    ObjectTracker,
    default_classes,
    table_for,
)

__all__ = ["FrameDetection", "Tracker", "TrackerParams"]

Range = tuple[float, float]


@dataclass(frozen=True)
class FrameDetection(Detection):
    """A Detection plus the frame it belongs to (its source node, seq, timestamp and size)."""

    source: str = ""
    seq: int = -1
    timestamp: float = 0.0
    size: tuple[int, int] = (0, 0)  # width, height of the frame

    @classmethod
    def of(cls, det: Detection, frame: Frame) -> FrameDetection:
        values = {f.name: getattr(det, f.name) for f in fields(Detection)}
        h, w = frame.data.shape[:2]
        return cls(
            **values, source=frame.source, seq=frame.seq, timestamp=frame.timestamp, size=(w, h)
        )


def _predefined(space: str) -> dict[str, ColourClass]:
    return {c.name: c for c in [*default_classes(space), *EXTRA_CLASSES[space]]}  # type: ignore[arg-type]


def _hint(word: str, options: list[str]) -> str:
    close = difflib.get_close_matches(word, options, n=1)
    return f"; did you mean {close[0]!r}?" if close else ""


class TrackerParams(BaseModel):
    """Params of the ``tracker`` node (see the module documentation)."""

    model_config = ConfigDict(extra="forbid")

    space: Literal["hsv", "ymp"] = "hsv"
    bins: Literal[16, 32, 64, 128, 256] = 64
    colours: dict[str, tuple[Range, Range, Range]] = Field(default_factory=dict)
    spec: ObjectSpec | None = None
    object: str = "ball"

    @model_validator(mode="before")
    @classmethod
    def _merge_spec(cls, data: Any) -> Any:
        """A partial ``spec`` overrides fields of the named object's spec."""
        if isinstance(data, dict):
            spec = data.get("spec")
            name = data.get("object", "ball")
            if isinstance(spec, dict) and "colour" not in spec and name in OBJECTS:
                data = {**data, "spec": {**OBJECTS[name].model_dump(), **spec}}
        return data

    @field_validator("colours")
    @classmethod
    def _check_colours(
        cls, colours: dict[str, tuple[Range, Range, Range]], info: ValidationInfo
    ) -> dict[str, tuple[Range, Range, Range]]:
        space, bins = info.data.get("space", "hsv"), info.data.get("bins", 64)
        for name, ranges in colours.items():
            # A class whose ranges hold no colour at all would silently never find anything.
            probe = ColourTable([ColourClass(name, space, ranges)], bins)
            if not probe.lut.any():
                raise ValueError(
                    f"colour class {name!r} matches no colour at all: its {space} ranges "
                    f"{[list(r) for r in ranges]} contain no (quantised) BGR colour"
                )
        return colours

    @field_validator("object")
    @classmethod
    def _check_object(cls, name: str, info: ValidationInfo) -> str:
        if "space" not in info.data or "colours" not in info.data or "spec" not in info.data:
            return name  # an earlier field is invalid: reported there
        spec: ObjectSpec | None = info.data["spec"]
        if spec is None:
            if name not in OBJECTS:
                raise ValueError(
                    f"unknown object {name!r} (known: {', '.join(sorted(OBJECTS))}; "
                    "or give a spec with a colour)" + _hint(name, list(OBJECTS))
                )
            spec = OBJECTS[name]
        space = info.data["space"]
        known = [*_predefined(space), *info.data["colours"]]
        for colour in [spec.colour, *(spec.surround.colours if spec.surround else ())]:
            if colour not in known:
                raise ValueError(
                    f"object {name!r} needs colour class {colour!r}, unknown in space {space} "
                    f"(known: {', '.join(dict.fromkeys(known))}; or define it under colours)"
                    + _hint(colour, known)
                )
        return name

    def custom_classes(self) -> dict[str, ColourClass]:
        return {n: ColourClass(n, self.space, r) for n, r in self.colours.items()}

    def object_spec(self) -> ObjectSpec:
        return self.spec if self.spec is not None else OBJECTS[self.object]

    def table(self) -> ColourTable:
        """The lookup table: the shared one when no custom colour is defined."""
        spec = self.object_spec()
        custom = self.custom_classes()
        if not custom:
            return table_for(spec, self.space, self.bins)
        # Custom classes first (they win where they overlap), then the predefined ones.
        rest = [c for n, c in _predefined(self.space).items() if n not in custom]
        return ColourTable([*custom.values(), *rest], self.bins)


class Tracker(Node):
    """Detects one object per activation in colour frames (see the module documentation)."""

    # what a swap over the control endpoint may change (flowrt kinds shows it)
    swappable = frozenset({"space", "bins", "colours", "spec", "object"})

    Params = TrackerParams

    frame = Input(Frame, doc="BGR (or RGB) uint8 frames")
    detection = Output(FrameDetection, doc="the object in that frame, found or not")

    def setup(self) -> None:
        p: TrackerParams = self.params
        self._tracker = ObjectTracker(p.object_spec(), p.table(), name=p.object)
        # Warm the code paths once (first calls into numpy/OpenCV are slow), so that the first
        # real activation meets its deadline; then forget what the warm-up saw.
        self._tracker.track(np.zeros((48, 64, 3), np.uint8))
        self._tracker.reset()
        self._warned = False
        self._t0 = self.ctx.now()

    def process(self, frame: Frame) -> FrameDetection:
        img = frame.data
        fmt = frame.pixel_format.upper()
        if fmt == "RGB" and img.ndim == 3 and img.shape[2] == 3:
            img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
        elif fmt != "BGR" or img.ndim != 3 or img.shape[2] != 3:
            self._bad_input(
                f"needs colour frames (BGR or RGB), got {fmt} {img.dtype} {tuple(img.shape)}; "
                "set pixel_format: BGR on the capture"
            )
            return self._nothing(frame)
        if img.dtype != np.uint8:
            self._bad_input(f"needs 8-bit frames, got {img.dtype}")
            return self._nothing(frame)
        return FrameDetection.of(self._tracker.track(img), frame)

    def _nothing(self, frame: Frame) -> FrameDetection:
        det = Detection(False, None, None, 0, 0.0, 0, self._tracker.name)
        return FrameDetection.of(det, frame)

    def _bad_input(self, detail: str) -> None:
        """Report once per node instance: a health event on the loop, a log line anywhere."""
        if self._warned:
            return
        self._warned = True
        self.ctx.log.warning("%s: bad input: %s", self.ctx.name, detail)
        with contextlib.suppress(RuntimeError):  # emit() exists only on the event loop
            t = self.ctx.now() - self._t0
            self.ctx.emit(HealthAlert(t, self.ctx.name, alert="bad-input", detail=detail))
