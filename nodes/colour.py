"""CAMBADA-style colour classification and object tracking.

Classification follows the CAMBADA vision system: colour classes are boxes in a perceptual
colour space (HSV, or the paper's YMP: luma, modulus and phase of the chroma vector), but an
image is never converted pixel by pixel. The classes are evaluated once over a quantised BGR
cube, giving a lookup table; classifying a pixel is then one table read, and a tracker only
classifies the pixels it looks at.

Tracking follows the paper's search: start where the object was last seen (else the image
centre), classify a small window there and look for pixels of the object's colour, grow the
region until it no longer touches the window border, validate it (area, aspect ratio, fill,
the colour of its surroundings), and only if that fails widen the window and finally search
the whole region of interest. The number of pixels classified is reported as the search
`cost`: an object that stayed put costs a small window, a lost one costs the full frame.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import Literal

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

__all__ = [
    "EXTRA_CLASSES",
    "OBJECTS",
    "REF_AREA",
    "ColourClass",
    "ColourSpace",
    "ColourTable",
    "Detection",
    "ObjectSpec",
    "ObjectTracker",
    "Surround",
    "colour_class",
    "convert",
    "default_classes",
    "default_table",
    "object_spec",
    "table_for",
    "track_sequence",
    "tracker_for",
]

ColourSpace = Literal["hsv", "ymp"]

#: Channel order per space; the angles (hsv's h, ymp's p) are the ranges that may wrap.
CHANNELS: dict[str, tuple[str, str, str]] = {"hsv": ("h", "s", "v"), "ymp": ("y", "m", "p")}


def convert(bgr: np.ndarray, space: ColourSpace) -> np.ndarray:
    """Convert BGR values (any shape ending in 3, 0..255) to `space`, as float32.

    hsv: H in degrees [0, 360), S and V in 0..255 (OpenCV's full-range convention, but with
    hue in degrees so that ranges read naturally). ymp: Y = luma 0..255, M = modulus of the
    (U, V) chroma vector (0..~160), P = its phase in degrees [0, 360).
    """
    v = np.asarray(bgr, dtype=np.float32)
    b, g, r = v[..., 0], v[..., 1], v[..., 2]
    out = np.empty(v.shape, dtype=np.float32)
    if space == "hsv":
        mx = np.maximum(np.maximum(b, g), r)
        mn = np.minimum(np.minimum(b, g), r)
        d = mx - mn
        safe = np.where(d > 0, d, 1.0)
        h = np.where(
            mx == r,
            ((g - b) / safe) % 6.0,
            np.where(mx == g, (b - r) / safe + 2.0, (r - g) / safe + 4.0),
        )
        out[..., 0] = np.where(d > 0, h * 60.0, 0.0) % 360.0
        out[..., 1] = np.where(mx > 0, 255.0 * d / np.where(mx > 0, mx, 1.0), 0.0)
        out[..., 2] = mx
    elif space == "ymp":
        y = 0.299 * r + 0.587 * g + 0.114 * b
        u = 0.492 * (b - y)
        vv = 0.877 * (r - y)
        out[..., 0] = y
        out[..., 1] = np.hypot(u, vv)
        out[..., 2] = np.degrees(np.arctan2(vv, u)) % 360.0
    else:
        raise ValueError(f"unknown colour space {space!r} (use 'hsv' or 'ymp')")
    return out


def _in_range(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """lo <= x <= hi, or, when lo > hi (a hue/phase range across 0 degrees), x >= lo or x <= hi."""
    if lo <= hi:
        return (x >= lo) & (x <= hi)
    return (x >= lo) | (x <= hi)


@dataclass(frozen=True)
class ColourClass:
    """A named box in a colour space; a range with lo > hi wraps (meant for hue/phase)."""

    name: str
    space: ColourSpace
    ranges: tuple[tuple[float, float], tuple[float, float], tuple[float, float]]

    def matches(self, values: np.ndarray) -> np.ndarray:
        """Which of the given values (already in this class's space, ... x 3) belong."""
        m = _in_range(values[..., 0], *self.ranges[0])
        m &= _in_range(values[..., 1], *self.ranges[1])
        m &= _in_range(values[..., 2], *self.ranges[2])
        return m

    def matches_bgr(self, bgr: np.ndarray) -> np.ndarray:
        """Exact per-pixel test of BGR values (the reference the lookup table approximates)."""
        return self.matches(convert(bgr, self.space))


def _hsv(name: str, h: tuple[float, float], s: tuple[float, float], v: tuple[float, float]):
    return ColourClass(name, "hsv", (h, s, v))


def _ymp(name: str, y: tuple[float, float], m: tuple[float, float], p: tuple[float, float]):
    return ColourClass(name, "ymp", (y, m, p))


_DEFAULTS: dict[str, list[ColourClass]] = {
    # Order is priority: a BGR cell matching two classes gets the earlier one.
    "hsv": [
        _hsv("orange", (8, 40), (150, 255), (90, 255)),
        _hsv("yellow", (45, 75), (120, 255), (110, 255)),
        _hsv("blue", (195, 250), (110, 255), (50, 255)),
        _hsv("green", (80, 165), (70, 255), (45, 255)),
        _hsv("white", (0, 360), (0, 55), (175, 255)),
        _hsv("black", (0, 360), (0, 255), (0, 60)),
    ],
    "ymp": [
        _ymp("orange", (50, 255), (55, 200), (105, 145)),
        _ymp("yellow", (110, 255), (45, 200), (145, 185)),
        _ymp("blue", (20, 255), (35, 200), (290, 345)),
        _ymp("green", (40, 255), (22, 200), (215, 280)),
        _ymp("white", (175, 255), (0, 20), (0, 360)),
        _ymp("black", (0, 55), (0, 200), (0, 360)),
    ],
}

#: Classes that are not part of the soccer set, for real footage. "amber" is the warm glow of
#: the table lamps in /work/shared/data/sample_720x528.avi: brighter and more saturated than the
#: skin it is lit next to, which sits at slightly lower hue and saturation.
EXTRA_CLASSES: dict[str, list[ColourClass]] = {
    "hsv": [_hsv("amber", (33, 65), (135, 255), (140, 255))],
    "ymp": [_ymp("amber", (110, 255), (50, 200), (130, 168))],
}


def default_classes(space: ColourSpace = "hsv") -> list[ColourClass]:
    """The soccer colours: orange (ball), yellow, blue, green (field), white, black."""
    if space not in _DEFAULTS:
        raise ValueError(f"unknown colour space {space!r} (use 'hsv' or 'ymp')")
    return list(_DEFAULTS[space])


def colour_class(name: str, space: ColourSpace = "hsv") -> ColourClass:
    """A predefined class (soccer defaults or EXTRA_CLASSES) by name."""
    for c in default_classes(space) + EXTRA_CLASSES[space]:
        if c.name == name:
            return c
    known = [c.name for c in default_classes(space) + EXTRA_CLASSES[space]]
    raise KeyError(f"no colour class {name!r} in space {space!r}; known: {known}")


class ColourTable:
    """A lookup table from quantised BGR to class labels (0 = unclassified, i + 1 = class i).

    Building evaluates every class on the centre of every BGR cell once (bins**3 cells, each
    channel quantised to 256 / bins levels); classifying a pixel is then a table read.
    """

    def __init__(self, classes: Sequence[ColourClass], bins: int = 64) -> None:
        if bins not in (16, 32, 64, 128, 256):
            raise ValueError(f"bins must be a power of two in 16..256, got {bins}")
        if len(classes) > 255:
            raise ValueError("at most 255 colour classes fit in a uint8 label")
        names = [c.name for c in classes]
        if len(set(names)) != len(names):
            raise ValueError(f"duplicate colour class names: {names}")
        self.classes = tuple(classes)
        self.names = tuple(names)
        self.bins = bins
        bits = bins.bit_length() - 1
        shift = 8 - bits
        centres = (np.arange(bins, dtype=np.float32) * (1 << shift)) + ((1 << shift) - 1) / 2.0
        b, g, r = np.meshgrid(centres, centres, centres, indexing="ij")
        cube = np.stack([b, g, r], axis=-1)
        lut = np.zeros((bins, bins, bins), dtype=np.uint8)
        converted: dict[str, np.ndarray] = {}
        for label in range(len(classes), 0, -1):  # reverse, so earlier classes win
            c = classes[label - 1]
            if c.space not in converted:
                converted[c.space] = convert(cube, c.space)
            lut[c.matches(converted[c.space])] = label
        self.lut = lut.ravel()
        # Per-channel index contributions: flat index = ib[b] + ig[g] + ir[r].
        levels = np.arange(256, dtype=np.int32) >> shift
        self._ib = levels << (2 * bits)
        self._ig = levels << bits
        self._ir = levels

    def label(self, name: str) -> int:
        """Label value of a class name."""
        try:
            return self.names.index(name) + 1
        except ValueError:
            raise KeyError(f"colour class {name!r} not in table {list(self.names)}") from None

    def classify(
        self, image: np.ndarray, window: tuple[int, int, int, int] | None = None
    ) -> np.ndarray:
        """Label image (uint8) of `image` (BGR uint8), or of the window (x0, y0, x1, y1) of it."""
        if window is not None:
            x0, y0, x1, y1 = window
            image = image[y0:y1, x0:x1]
        idx = self._ib[image[..., 0]]
        idx += self._ig[image[..., 1]]
        idx += self._ir[image[..., 2]]
        return self.lut[idx]


@lru_cache(maxsize=8)
def default_table(space: ColourSpace = "hsv", bins: int = 64) -> ColourTable:
    """The shared table of the soccer colours (built once per process and space)."""
    return ColourTable(default_classes(space), bins)


# ---------------------------------------------------------------------- object specs

#: ObjectSpec.max_area is in pixels of a 320x240 image and scales with the image area, so one
#: spec serves every resolution; min_area is a noise floor in absolute pixels (a sliver of the
#: ball at the image edge is as small at any resolution).
REF_AREA = 320 * 240


class Surround(BaseModel):
    """The object must be embedded in these colours (e.g. the ball lies on the carpet).

    A ring of `width` x (larger bbox side) pixels (at least 2) around the bounding box is
    classified; at least `min_fraction` of its in-image pixels must belong to `colours`.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    colours: tuple[str, ...]
    min_fraction: float = Field(0.5, ge=0.0, le=1.0)
    width: float = Field(0.25, gt=0.0, le=2.0)


class ObjectSpec(BaseModel):
    """What an object looks like to the tracker.

    kind "blob": one connected region of `colour`, validated by area, aspect (w / h), fill
    (area / bbox area) and surroundings. `min_area` is in pixels; `max_area` in pixels of a
    320x240 image (scaled with the image area). kind "pixels": all pixels of `colour` in the region
    of interest together (field lines: their centroid and count, no shape).
    `roi` is (x0, y0, x1, y1) as fractions of the image, for objects known to appear only in
    part of it (obstacles in the lower part of a front camera's image).
    `centroid` (blobs): "silhouette" (default) reports the centre of the region's outer
    contour with its holes filled, so printing, labels or highlights inside an object do not
    pull its position off; "pixels" reports the mean of the matching pixels (the paper's).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    colour: str
    kind: Literal["blob", "pixels"] = "blob"
    min_area: float = Field(20.0, ge=1.0)
    max_area: float | None = None
    min_aspect: float = Field(0.0, ge=0.0)
    max_aspect: float | None = None
    min_fill: float = Field(0.0, ge=0.0, le=1.0)
    surround: Surround | None = None
    roi: tuple[float, float, float, float] | None = None
    centroid: Literal["silhouette", "pixels"] = "silhouette"

    @model_validator(mode="after")
    def _check(self) -> ObjectSpec:
        if self.max_area is not None and self.max_area < self.min_area:
            raise ValueError("max_area must be >= min_area")
        if self.max_aspect is not None and self.max_aspect < self.min_aspect:
            raise ValueError("max_aspect must be >= min_aspect")
        if self.roi is not None:
            x0, y0, x1, y1 = self.roi
            if not (0.0 <= x0 < x1 <= 1.0 and 0.0 <= y0 < y1 <= 1.0):
                raise ValueError("roi must be (x0, y0, x1, y1) with 0 <= x0 < x1 <= 1, same for y")
        return self


_FIELD = Surround(colours=("green", "white", "black"), min_fraction=0.4)

#: Object specs of the soccer graph, plus "candle" for the real sample video.
_POST = ObjectSpec(  # corner posts: thin, upright, above the horizon; the colour varies
    colour="blue",
    min_area=20,
    max_area=140,
    min_aspect=0.15,
    max_aspect=4.0,
    min_fill=0.4,
    roi=(0.0, 0.0, 1.0, 0.5),
)

OBJECTS: dict[str, ObjectSpec] = {
    "ball": ObjectSpec(
        colour="orange",
        min_area=20,
        max_area=1500,
        min_aspect=0.2,
        max_aspect=5.0,
        surround=_FIELD,
    ),
    "blue_goal": ObjectSpec(colour="blue", min_area=150, max_aspect=1.2, min_fill=0.5),
    "yellow_goal": ObjectSpec(colour="yellow", min_area=150, max_aspect=1.2, min_fill=0.5),
    "blue_post": _POST.model_copy(update={"colour": "blue"}),
    "yellow_post": _POST.model_copy(update={"colour": "yellow"}),
    "obstacle": ObjectSpec(
        colour="black",
        min_area=100,
        max_area=6000,
        min_aspect=0.2,
        max_aspect=5.0,
        roi=(0.0, 0.25, 1.0, 1.0),
    ),
    "line": ObjectSpec(colour="white", kind="pixels", min_area=50),
    # The glowing table lamp in the real sample video (amber, a tall cylinder).
    "candle": ObjectSpec(
        colour="amber",
        min_area=300,
        min_aspect=0.3,
        max_aspect=2.5,
        min_fill=0.45,
    ),
}


def object_spec(colour: str, **fields: object) -> ObjectSpec:
    """A blob spec for `colour` with permissive defaults; override any field by keyword."""
    return ObjectSpec(colour=colour, **fields)  # type: ignore[arg-type]


def table_for(spec: ObjectSpec, space: ColourSpace = "hsv", bins: int = 64) -> ColourTable:
    """A table that knows every class the spec needs: the shared soccer table when it suffices,
    else one built from the predefined classes (so extra classes never steal soccer colours)."""
    needed = [spec.colour, *(spec.surround.colours if spec.surround else ())]
    table = default_table(space, bins)
    if all(n in table.names for n in needed):
        return table
    return ColourTable([colour_class(n, space) for n in dict.fromkeys(needed)], bins)


# ---------------------------------------------------------------------- tracking


@dataclass(frozen=True)
class Detection:
    """Result of one tracking step; `cost` counts the pixels classified to get it."""

    found: bool
    centroid: tuple[float, float] | None
    bbox: tuple[int, int, int, int] | None  # x, y, w, h
    area: int
    confidence: float
    cost: int
    object: str = ""


@dataclass
class _Candidate:
    centroid: tuple[float, float]
    bbox: tuple[int, int, int, int]
    area: int
    mask: np.ndarray | None = None  # the component's pixels inside its bbox (for silhouettes)


def silhouette_centroid(mask: np.ndarray) -> tuple[float, float] | None:
    """Centre of the outer contour of ``mask`` (uint8, nonzero = object) with holes filled."""
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    if not contours:
        return None
    filled = np.zeros(mask.shape, np.uint8)
    cv2.drawContours(filled, contours, -1, 1, thickness=cv2.FILLED)
    m = cv2.moments(filled, binaryImage=True)
    if m["m00"] <= 0:
        return None
    return m["m10"] / m["m00"], m["m01"] / m["m00"]


Window = tuple[int, int, int, int]  # x0, y0, x1, y1 (exclusive)


class ObjectTracker:
    """Tracks one object across frames with the CAMBADA windowed search (see module doc).

    The tracker is stateful (last position and velocity) and not thread-safe; use one per
    object and camera.
    """

    #: Consecutive misses after which the last position is forgotten and search restarts
    #: from the centre of the region of interest.
    FORGET_AFTER = 10
    #: Maximum number of times a window is enlarged to contain a region touching its border.
    MAX_GROW = 4

    def __init__(self, spec: ObjectSpec, table: ColourTable, name: str = "") -> None:
        self.spec = spec
        self.table = table
        self.name = name or spec.colour
        self.label = table.label(spec.colour)
        self._surround_labels = (
            np.array([table.label(c) for c in spec.surround.colours], dtype=np.uint8)
            if spec.surround
            else None
        )
        self.reset()

    def reset(self) -> None:
        """Forget the object's history: the next search starts from the centre."""
        self._last: _Candidate | None = None
        self._velocity = (0.0, 0.0)
        self._misses = 0

    @property
    def last(self) -> tuple[float, float] | None:
        """Last known centroid, if the object has not been lost for long."""
        return self._last.centroid if self._last else None

    # -- helpers

    def _roi(self, w: int, h: int) -> Window:
        if self.spec.roi is None:
            return 0, 0, w, h
        x0, y0, x1, y1 = self.spec.roi
        return round(x0 * w), round(y0 * h), max(round(x1 * w), 1), max(round(y1 * h), 1)

    def _components(
        self, image: np.ndarray, win: Window, roi: Window
    ) -> tuple[list[_Candidate], Window, int]:
        """Regions of the object's colour in `win`, growing the window while a region touches a
        border that can still move (region growing, done by re-classifying a larger window)."""
        cost = 0
        min_part = max(2, int(self.spec.min_area) // 10)
        for _ in range(self.MAX_GROW + 1):
            x0, y0, x1, y1 = win
            labels = self.table.classify(image, win)
            cost += labels.size
            mask = (labels == self.label).view(np.uint8)
            n, comp, stats, cents = cv2.connectedComponentsWithStats(mask, connectivity=8)
            cands = [
                _Candidate(
                    (float(cents[i][0]) + x0, float(cents[i][1]) + y0),
                    (
                        int(stats[i][0]) + x0,
                        int(stats[i][1]) + y0,
                        int(stats[i][2]),
                        int(stats[i][3]),
                    ),
                    int(stats[i][4]),
                    comp[
                        stats[i][1] : stats[i][1] + stats[i][3],
                        stats[i][0] : stats[i][0] + stats[i][2],
                    ]
                    == i,
                )
                for i in range(1, n)
            ]
            grow = list(win)
            touching = []
            for i in range(1, n):
                cx, cy, cw, ch, area = (int(v) for v in stats[i])
                if area < min_part:
                    continue
                edges = (
                    cx == 0 and x0 > roi[0],
                    cy == 0 and y0 > roi[1],
                    cx + cw == x1 - x0 and x1 < roi[2],
                    cy + ch == y1 - y0 and y1 < roi[3],
                )
                if any(edges):
                    touching.append((i, edges))
                elif self._shape_ok(cands[i - 1]):
                    # A complete plausible region is here: like the paper's search, stop
                    # rather than grow after other regions cut by the window border.
                    return cands, win, cost
            for i, edges in touching:
                cx, cy, cw, ch, _ = (int(v) for v in stats[i])
                if edges[0]:
                    grow[0] = max(roi[0], x0 - 2 * cw - 4)
                if edges[1]:
                    grow[1] = max(roi[1], y0 - 2 * ch - 4)
                if edges[2]:
                    grow[2] = min(roi[2], x1 + 2 * cw + 4)
                if edges[3]:
                    grow[3] = min(roi[3], y1 + 2 * ch + 4)
            if tuple(grow) == win:
                break
            win = (grow[0], grow[1], grow[2], grow[3])
        return cands, win, cost

    def _shape_ok(self, c: _Candidate) -> bool:
        s = self.spec
        if c.area < s.min_area:
            return False
        if s.max_area is not None and c.area > s.max_area * self._scale:
            return False
        _, _, w, h = c.bbox
        aspect = w / h
        if aspect < s.min_aspect or (s.max_aspect is not None and aspect > s.max_aspect):
            return False
        return c.area / (w * h) >= s.min_fill

    def _surround_fraction(self, image: np.ndarray, c: _Candidate) -> tuple[float, int]:
        """Fraction of the ring around the bbox in the surround colours, and pixels classified."""
        assert self.spec.surround is not None
        assert self._surround_labels is not None
        x, y, w, h = c.bbox
        r = max(2, round(self.spec.surround.width * max(w, h)))
        ih, iw = image.shape[:2]
        x0, y0 = max(0, x - r), max(0, y - r)
        x1, y1 = min(iw, x + w + r), min(ih, y + h + r)
        labels = self.table.classify(image, (x0, y0, x1, y1))
        ring = np.ones(labels.shape, dtype=bool)
        ring[y - y0 : y - y0 + h, x - x0 : x - x0 + w] = False
        total = int(ring.sum())
        if total == 0:
            return 1.0, labels.size
        good = int(np.isin(labels[ring], self._surround_labels).sum())
        return good / total, labels.size

    def _validate(
        self, image: np.ndarray, cands: list[_Candidate], point: tuple[float, float] | None
    ) -> tuple[_Candidate | None, float, int]:
        """Best valid candidate (nearest to `point`, else largest), its confidence, the cost."""
        if point is None:
            order = sorted(cands, key=lambda c: -c.area)
        else:
            px, py = point
            order = sorted(
                cands, key=lambda c: (c.centroid[0] - px) ** 2 + (c.centroid[1] - py) ** 2
            )
        cost = 0
        for c in order:
            if not self._shape_ok(c):
                continue
            # Confidence: small blobs (near the noise floor) and poorly embedded ones score low.
            conf = min(1.0, c.area / (3.0 * self.spec.min_area))
            if self.spec.surround is not None:
                frac, n = self._surround_fraction(image, c)
                cost += n
                if frac < self.spec.surround.min_fraction:
                    continue
                conf *= min(1.0, 0.5 + frac)
            return c, conf, cost
        return None, 0.0, cost

    def _found(self, c: _Candidate, conf: float, cost: int, near: bool) -> Detection:
        if self.spec.centroid == "silhouette" and c.mask is not None:
            centre = silhouette_centroid(c.mask.view(np.uint8))
            if centre is not None:
                c.centroid = (centre[0] + c.bbox[0], centre[1] + c.bbox[1])
            c.mask = None  # the tracker keeps the candidate: not its pixels
        # Velocity only from consecutive detections in the first window around the prediction:
        # a re-acquisition further away (another object, a scene cut) says nothing about motion.
        if near and self._last is not None and self._misses == 0:
            self._velocity = (
                c.centroid[0] - self._last.centroid[0],
                c.centroid[1] - self._last.centroid[1],
            )
        else:
            self._velocity = (0.0, 0.0)
        self._last, self._misses = c, 0
        return Detection(True, c.centroid, c.bbox, c.area, conf, cost, self.name)

    def _lost(self, cost: int) -> Detection:
        self._misses += 1
        if self._misses >= self.FORGET_AFTER:
            self._last = None
        self._velocity = (0.0, 0.0)
        return Detection(False, None, None, 0, 0.0, cost, self.name)

    # -- public

    def track(self, image: np.ndarray) -> Detection:
        """Find the object in `image` (BGR uint8), starting where it was last seen."""
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise ValueError(f"expected a BGR uint8 image, got {image.dtype} {image.shape}")
        h, w = image.shape[:2]
        self._scale = (w * h) / REF_AREA
        roi = self._roi(w, h)
        if self.spec.kind == "pixels":
            return self._track_pixels(image, roi)

        cost = 0
        if self._last is not None:
            vx, vy = self._velocity
            point = (self._last.centroid[0] + vx, self._last.centroid[1] + vy)
            _, _, bw, bh = self._last.bbox
            half = max(bw, bh) / 2 + max(8.0, 0.05 * max(w, h)) + math.hypot(vx, vy) / 2
        else:
            point = ((roi[0] + roi[2]) / 2, (roi[1] + roi[3]) / 2)
            half = max(8.0, 0.125 * max(w, h))
        full_area = (roi[2] - roi[0]) * (roi[3] - roi[1])
        # Windows pay off only while the object was seen in the previous frame (or at the very
        # start, where the centre is the best guess); once it is lost, the windows would just
        # be classified twice, so a lost object costs exactly one full search per frame.
        levels = 2 if self._misses == 0 else 0
        for level in range(levels):  # the window, then twice as large, then the whole roi
            hw = half * (2**level)
            win = (
                max(roi[0], math.floor(point[0] - hw)),
                max(roi[1], math.floor(point[1] - hw)),
                min(roi[2], math.ceil(point[0] + hw) + 1),
                min(roi[3], math.ceil(point[1] + hw) + 1),
            )
            if win[0] >= win[2] or win[1] >= win[3]:
                continue
            if (win[2] - win[0]) * (win[3] - win[1]) >= full_area // 2:
                break  # as costly as the full search: do that instead
            cands, _, n = self._components(image, win, roi)
            cost += n
            # Tracking: prefer the region nearest the prediction; re-acquiring: the largest.
            best, conf, n = self._validate(image, cands, point if self._last else None)
            cost += n
            if best is not None:
                return self._found(best, conf, cost, near=level == 0)
        cands, _, n = self._components(image, roi, roi)
        cost += n
        best, conf, n = self._validate(image, cands, None)
        cost += n
        if best is not None:
            return self._found(best, conf, cost, near=False)
        return self._lost(cost)

    def _track_pixels(self, image: np.ndarray, roi: Window) -> Detection:
        """All pixels of the class in the roi: centroid, bbox and count (field lines)."""
        labels = self.table.classify(image, roi)
        mask = (labels == self.label).view(np.uint8)
        m = cv2.moments(mask, binaryImage=True)
        area = int(m["m00"])
        if area < self.spec.min_area:
            return Detection(False, None, None, area, 0.0, labels.size, self.name)
        x, y, bw, bh = cv2.boundingRect(mask)
        centroid = (m["m10"] / m["m00"] + roi[0], m["m01"] / m["m00"] + roi[1])
        conf = min(1.0, area / (4.0 * self.spec.min_area))
        return Detection(
            True, centroid, (x + roi[0], y + roi[1], bw, bh), area, conf, labels.size, self.name
        )


def tracker_for(
    name: str, space: ColourSpace = "hsv", bins: int = 64, spec: ObjectSpec | None = None
) -> ObjectTracker:
    """A tracker for a named object of OBJECTS (or for `spec`), with a suitable table."""
    if spec is None:
        if name not in OBJECTS:
            raise KeyError(f"unknown object {name!r}; known: {sorted(OBJECTS)}")
        spec = OBJECTS[name]
    return ObjectTracker(spec, table_for(spec, space, bins), name=name)


def track_sequence(frames: Iterable[np.ndarray], tracker: ObjectTracker) -> list[Detection]:
    """Run a tracker over frames in order (real footage, recorded sequences)."""
    return [tracker.track(f) for f in frames]
