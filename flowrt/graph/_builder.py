"""Building a graph in Python: the same model, the same checks as a YAML file.

g = GraphBuilder("demo")
g.add("cam", "capture", params={"fps": 20})
g.add("ball", Tracker, trigger=FrameTrigger(frame="cam"), inputs={"frame": "cam.frame"})
graph = g.build()
"""

from __future__ import annotations

from typing import Any

from ..node import Node
from ._resolve import Graph, resolve
from .spec import GraphSpec, ModeSpec, Trigger


class GraphBuilder:
    def __init__(self, name: str = "graph", description: str = "") -> None:
        self.name = name
        self.description = description
        self._nodes: dict[str, dict[str, Any]] = {}
        self._kinds: dict[str, type[Node]] = {}
        self._modes: dict[str, ModeSpec] = {}
        self._remote: dict[str, Any] = {}

    def add(
        self,
        name: str,
        kind: str | type[Node],
        *,
        params: dict[str, Any] | None = None,
        trigger: Trigger | dict[str, Any] | str | None = None,
        inputs: dict[str, Any] | None = None,
        **timing: Any,
    ) -> GraphBuilder:
        """Add a node; ``timing`` takes the NodeSpec fields (deadline, priority, placement...)."""
        if name in self._nodes:
            raise ValueError(f"duplicate node name {name!r}")
        if isinstance(kind, type):
            key = f"{kind.__module__}:{kind.__qualname__}"
            self._kinds[key] = kind
            kind = key
        fields: dict[str, Any] = {
            "kind": kind,
            "params": params or {},
            "inputs": inputs or {},
            **timing,
        }
        if trigger is not None:
            fields["trigger"] = trigger
        self._nodes[name] = fields
        return self

    def mode(self, name: str, **overrides: dict[str, Any]) -> GraphBuilder:
        self._modes[name] = ModeSpec.model_validate({"nodes": overrides})
        return self

    def zenoh(self, **settings: Any) -> GraphBuilder:
        """The Zenoh session of a graph that spans machines (the ``zenoh:`` section)."""
        self._remote["zenoh"] = settings
        return self

    def export(self, key: str, source: str | dict[str, Any]) -> GraphBuilder:
        """Publish ``node.port`` under the Zenoh key ``key`` (an ``export:`` entry)."""
        self._remote.setdefault("export", {})[key] = source
        return self

    def import_(self, name: str, key: str | dict[str, Any]) -> GraphBuilder:
        """A remote stream as node ``name`` with output ``output`` (an ``import:`` entry)."""
        self._remote.setdefault("import", {})[name] = key
        return self

    def spec(self) -> GraphSpec:
        return GraphSpec.model_validate(
            {
                "name": self.name,
                "description": self.description,
                "nodes": self._nodes,
                "modes": self._modes,
                **self._remote,
            }
        )

    def build(self) -> Graph:
        """Validate and resolve; raises GraphError listing every problem."""
        from ._loading import Locations, check_data
        from .diagnostics import GraphError

        data = {
            "name": self.name,
            "description": self.description,
            "nodes": self._nodes,
            **self._remote,
        }
        if self._modes:
            data["modes"] = {k: v.model_dump(exclude_none=True) for k, v in self._modes.items()}
        loaded = check_data(data, Locations("<python>"))
        if loaded.spec is None:
            raise GraphError(loaded.errors)
        return resolve(
            loaded.spec,
            loaded.locs,
            self._kinds,
            earlier=loaded.errors,
            invalid_nodes=loaded.invalid_nodes,
        )

    @property
    def kinds(self) -> dict[str, type[Node]]:
        return dict(self._kinds)
