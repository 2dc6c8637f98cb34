"""The Town object, the contract between a town file and the router and renderer: roads, junctions,
buildings, props, style and bounds; and TownError, the one error a bad town file raises."""
from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from cicfw.core.errors import CicfwError


class TownError(CicfwError):
    """A town file that cannot be built; the message names the file, the element and the fix."""


@dataclass(frozen=True, eq=False)
class Style:
    """Colours as (R, G, B) ints 0-255."""

    road: tuple
    marking: tuple
    centre_line: tuple
    sidewalk: tuple
    terrain: tuple
    facades: tuple
    roof: tuple
    vegetation: tuple
    pole: tuple
    sky: tuple


@dataclass(frozen=True, eq=False)
class Road:
    """A two-way road; ``centreline`` runs from node ``a``'s junction edge to node ``b``'s (0.5 m step)."""

    id: str
    a: str
    b: str
    centreline: np.ndarray  # (M, 2)
    length: float = 0.0


@dataclass(frozen=True, eq=False)
class Junction:
    """A junction at node ``id``: paved polygon (CCW) and the roads meeting there (3 = T, 4 = X)."""

    id: str
    centre: np.ndarray
    polygon: np.ndarray
    arms: tuple
    radius: float = 0.0  # distance from the centre to where the arms' centrelines start


@dataclass(frozen=True, eq=False)
class Building:
    footprint: np.ndarray  # (K, 2) CCW
    height: float
    facade: int  # index into style.facades


@dataclass(frozen=True, eq=False)
class Prop:
    kind: str  # "tree" | "pole"
    position: np.ndarray
    height: float
    radius: float


@dataclass(frozen=True, eq=False)
class Town:
    name: str
    lane_width: float
    sidewalk_width: float
    roads: tuple
    junctions: tuple
    buildings: tuple
    props: tuple
    style: Style
    bounds: tuple  # xmin, ymin, xmax, ymax including margins
    nodes: dict = field(default_factory=dict)  # node id -> (2,) position
    source: str = ""

    def road(self, road_id: str) -> Road:
        return self._roads_by_id[road_id]

    def junction(self, node_id: str) -> Junction:
        return self._junctions_by_id[node_id]

    @functools.cached_property
    def _roads_by_id(self) -> dict:
        return {r.id: r for r in self.roads}

    @functools.cached_property
    def _junctions_by_id(self) -> dict:
        return {j.id: j for j in self.junctions}
