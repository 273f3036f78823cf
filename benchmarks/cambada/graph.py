"""The benchmark's graph: graphs/cambada.yaml with recording (or calibrated) tracker kinds.

Timing (period, phase, priority, deadline, placement, watchdog), cameras and modes are kept
exactly; only the trackers' ``kind`` changes (recording, or paper-calibrated), the cameras' kind
may change (``capture``: ``builtin`` keeps the built-in node, ``warm`` simulates the scene's
motion at setup rather than mid-run, ``ahead`` also renders each frame ahead of its timer; the
same frames in every case, see :mod:`benchmarks.cambada.nodes`), and the live-view ``display``
node is dropped (a web server has no place in a timing benchmark). The monolithic loop reads
the same derived file for its cameras and tasks, so both architectures run the same workload.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

ROOT = Path(__file__).resolve().parents[2]
SOURCE = ROOT / "graphs" / "cambada.yaml"
KINDS = {
    "real": "benchmarks.cambada.nodes:RecordingTracker",
    "calibrated": "benchmarks.cambada.nodes:CalibratedTracker",
}
CAPTURES = {
    "builtin": "capture",
    "warm": "benchmarks.cambada.nodes:WarmCapture",
    "ahead": "benchmarks.cambada.nodes:AheadCapture",
}
CRITICAL = ("avoid_fr", "avoid_om", "ball_om", "ball_fr")


def derive(regime: str, record_dir: Path, out: Path, seed: int = 0, capture: str = "ahead") -> Path:
    """Write the benchmark graph for ``regime`` (``real`` or ``calibrated``) to ``out``."""
    doc = yaml.safe_load(SOURCE.read_text())
    doc["nodes"].pop("display", None)
    doc["name"] = f"cambada-bench-{regime}"
    for node in doc["nodes"].values():
        if node["kind"] == "capture":
            node["kind"] = CAPTURES[capture]
        if node["kind"] != "tracker":
            continue
        node["kind"] = KINDS[regime]
        params = dict(node.get("params") or {})
        params["record_dir"] = str(record_dir)
        if regime == "calibrated":
            params = {"object": params["object"], "seed": seed, "record_dir": str(record_dir)}
        node["params"] = params
    out.write_text(yaml.safe_dump(doc, sort_keys=False))
    return out


@dataclass(frozen=True)
class Task:
    name: str
    kind: str
    params: dict[str, Any]
    camera: str
    period: int
    phase: int
    priority: int
    deadline_ms: float | None
    order: int


@dataclass(frozen=True)
class Camera:
    name: str
    params: dict[str, Any]
    phase_ms: float  # timer phase of the capture node
    capture: str  # builtin, warm or ahead (see CAPTURES)


def load(path: Path) -> tuple[dict[str, Camera], list[Task]]:
    """Cameras and tracker tasks of a (derived) graph, tasks in flowrt's dispatch order."""
    doc = yaml.safe_load(Path(path).read_text())
    cams: dict[str, Camera] = {}
    tasks: list[Task] = []
    for order, (name, node) in enumerate(doc["nodes"].items()):
        trig = node.get("trigger") or {}
        capture = {kind: name for name, kind in CAPTURES.items()}.get(node["kind"])
        if capture is not None:
            phase = _ms(trig.get("phase", 0))
            cams[name] = Camera(name, node.get("params") or {}, phase, capture)
        elif "frame" in trig:
            dl = node.get("deadline")
            tasks.append(
                Task(
                    name,
                    node["kind"],
                    node.get("params") or {},
                    trig["frame"],
                    int(trig.get("period", 1)),
                    int(trig.get("phase", 0)),
                    int(node.get("priority", 50)),
                    None if dl is None else _ms(dl),
                    order,
                )
            )
    tasks.sort(key=lambda t: (-t.priority, t.order))
    return cams, tasks


def modes(path: Path = SOURCE) -> dict[str, Any]:
    return dict(yaml.safe_load(Path(path).read_text()).get("modes") or {})


def _ms(value: Any) -> float:
    if isinstance(value, int | float):
        return float(value)
    s = str(value).strip()
    for unit, scale in (("ms", 1.0), ("us", 0.001), ("s", 1000.0)):
        if s.endswith(unit):
            return float(s[: -len(unit)]) * scale
    return float(s)
