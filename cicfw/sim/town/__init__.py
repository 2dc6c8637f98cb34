"""Towns as data: load a town YAML file (``conf/town/<name>.yaml``), validate it, build its geometry.

A town file lists nodes (junction centres), two-way roads between them (optionally bent through
``via`` points with rounded corners), the lane and sidewalk widths, a style, and compact rules that
generate buildings and props deterministically from a seed. ``load_town`` returns a ``Town`` (see
``/work/notes/TOWN_CONTRACT.md`` and docs/simulator.md); any mistake in the file raises one
``TownError`` naming the element. Coordinates: metres, x east, y north, yaw CCW from +x.

Modules: ``model`` (the ``Town`` object and ``TownError``), ``files`` (shipped names and paths, loading),
``fields`` (the file's schema and its checks), ``layout`` (``build_town``: nodes, roads, junctions,
bounds), ``dressing`` (buildings and props) and ``geometry`` (the plane helpers they share).
"""
from __future__ import annotations

from cicfw.sim.town.files import load_town, town_names, town_path
from cicfw.sim.town.geometry import STEP, resample
from cicfw.sim.town.layout import MAX_TOWN_SIDE_M, MIN_ARM_ANGLE_DEG, MIN_ROAD_LENGTH, build_town
from cicfw.sim.town.model import Building, Junction, Prop, Road, Style, Town, TownError

__all__ = [
    "MAX_TOWN_SIDE_M", "MIN_ARM_ANGLE_DEG", "MIN_ROAD_LENGTH", "STEP", "Building", "Junction", "Prop", "Road",
    "Style", "Town", "TownError", "build_town", "load_town", "resample", "town_names", "town_path",
]
