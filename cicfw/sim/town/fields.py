"""A town file's schema: the fields each section accepts, and reading them with one ``TownError`` per
bad field, naming the file, the element and what is accepted."""
from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from cicfw.sim.town.model import Style, TownError

TOP_KEYS = {
    "name", "lane_width", "sidewalk_width", "junction_radius", "margin", "style",
    "nodes", "roads", "buildings", "props",
}
STYLE_KEYS = tuple(f.name for f in dataclasses.fields(Style))  # every colour a style names
ROAD_KEYS = {"id", "a", "b", "via", "radius", "frontage"}
FRONTAGES = ("buildings", "trees", "none")
BUILDING_KEYS = {"seed", "setback", "width", "depth", "height", "gap", "fill", "list"}
PROP_KEYS = {"seed", "trees", "poles", "list"}


class FieldReader:
    """Reads a town spec's fields, each checked, raising one TownError prefixed with the file (``source``)."""

    def __init__(self, source: str) -> None:
        self.source = source

    def fail(self, msg: str) -> None:
        raise TownError(f"{self.source}: {msg}")

    def keys(self, d: Any, allowed: set, where: str) -> dict:
        if not isinstance(d, dict):
            self.fail(f"{where} must be a mapping, got {type(d).__name__}")
        extra = sorted(set(map(str, d)) - allowed)
        if extra:
            self.fail(f"{where}: unknown field {extra[0]!r}; accepted fields: {', '.join(sorted(allowed))}")
        return d

    def num(self, d: dict, key: str, where: str, default: Any = None, lo: float | None = None,
            hi: float | None = None) -> float:
        v = d.get(key, default)
        if v is None:
            self.fail(f"{where}: missing field {key!r} (a number)")
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            self.fail(f"{where}.{key} must be a number, got {v!r}")
        if lo is not None and v < lo or hi is not None and v > hi:
            self.fail(f"{where}.{key} = {v!r} is out of range [{lo}, {hi}]")
        return float(v)

    def rng(self, d: dict, key: str, where: str, default: Any, lo: float = 0.0) -> tuple:
        v = d.get(key, default)
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            v = [v, v]
        if (not isinstance(v, (list, tuple)) or len(v) != 2
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)
                or v[0] > v[1] or v[0] < lo):
            self.fail(f"{where}.{key} must be a number or a range [low, high] with {lo} <= low <= high, got {v!r}")
        return float(v[0]), float(v[1])

    def point(self, v: Any, where: str) -> np.ndarray:
        if (not isinstance(v, (list, tuple)) or len(v) != 2
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)):
            self.fail(f"{where} must be a point [x, y] in metres, got {v!r}")
        return np.array(v, dtype=float)

    def colour(self, v: Any, where: str) -> tuple:
        if (not isinstance(v, (list, tuple)) or len(v) != 3
                or not all(isinstance(x, int) and not isinstance(x, bool) and 0 <= x <= 255 for x in v)):
            self.fail(f"{where} must be a colour [R, G, B] with ints 0-255, got {v!r}")
        return tuple(int(x) for x in v)


def read_style(cx: FieldReader, s: Any) -> Style:
    """The ``style`` section: every colour named in STYLE_KEYS, ``facades`` a non-empty list of them."""
    cx.keys(s, set(STYLE_KEYS), "style")
    vals = {}
    for k in STYLE_KEYS:
        if k not in s:
            cx.fail(f"style: missing colour {k!r} (needs: {', '.join(STYLE_KEYS)})")
        if k == "facades":
            f = s[k]
            if not isinstance(f, list) or not f:
                cx.fail("style.facades must be a non-empty list of colours [[R, G, B], ...]")
            vals[k] = tuple(cx.colour(c, f"style.facades[{i}]") for i, c in enumerate(f))
        else:
            vals[k] = cx.colour(s[k], f"style.{k}")
    return Style(**vals)
