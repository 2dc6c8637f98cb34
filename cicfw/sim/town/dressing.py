"""Buildings and props placed along the roads from the town file's seeded rules (and its explicit lists),
never on the road, a junction, a sidewalk or each other (an occupancy grid)."""
from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np

from cicfw.sim.town.fields import BUILDING_KEYS, PROP_KEYS, FieldReader
from cicfw.sim.town.geometry import frames_at, polygon_area, rect
from cicfw.sim.town.model import Building, Prop, Road, Style


class Occupancy:
    """A 0.5 m grid of what is taken (road, junction, sidewalk, buildings) for placing buildings/props."""

    RES = 0.5

    def __init__(self, bounds: tuple, roads: list[Road], junctions: tuple, hw: float, sw: float) -> None:
        self.x0, self.y0 = bounds[0], bounds[1]
        w = int(math.ceil((bounds[2] - bounds[0]) / self.RES)) + 1
        h = int(math.ceil((bounds[3] - bounds[1]) / self.RES)) + 1
        paved = np.zeros((h, w), np.uint8)
        for r in roads:
            pts = self.px(r.centreline)
            cv2.polylines(paved, [pts], False, 1, thickness=max(int(round(2 * hw / self.RES)), 1))
        for j in junctions:
            cv2.fillPoly(paved, [self.px(j.polygon)], 1)
        k = int(round((sw + 0.5) / self.RES))
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * k + 1, 2 * k + 1))
        self.grid = cv2.dilate(paved, kernel)

    def px(self, pts: np.ndarray) -> np.ndarray:
        q = (np.asarray(pts) - (self.x0, self.y0)) / self.RES
        return np.round(q).astype(np.int32).reshape(-1, 1, 2)

    def free_poly(self, poly: np.ndarray) -> bool:
        mask = np.zeros_like(self.grid)
        p = self.px(poly)
        x0, y0 = p[:, 0, 0].min(), p[:, 0, 1].min()
        x1, y1 = p[:, 0, 0].max() + 1, p[:, 0, 1].max() + 1
        if x0 < 0 or y0 < 0 or y1 > self.grid.shape[0] or x1 > self.grid.shape[1]:
            return False
        cv2.fillConvexPoly(mask[y0:y1, x0:x1], np.ascontiguousarray(p - (x0, y0)), 1)
        return not np.any(self.grid[y0:y1, x0:x1] & mask[y0:y1, x0:x1])

    def take_poly(self, poly: np.ndarray) -> None:
        cv2.fillConvexPoly(self.grid, self.px(poly), 1)

    def free_disc(self, c: np.ndarray, r: float) -> bool:
        return self.free_poly(rect(c, np.array([1.0, 0.0]), 2 * r, 2 * r))

    def take_disc(self, c: np.ndarray, r: float) -> None:
        cv2.circle(self.grid, tuple(int(v) for v in self.px(c[None])[0, 0]), int(math.ceil(r / self.RES)), 1, -1)


def place_buildings(cx: FieldReader, spec: Any, roads: list[Road], frontage: dict, hw: float, sw: float,
                    occ: Occupancy, style: Style) -> list[Building]:
    """The file's listed buildings, then rows of them behind the sidewalks of roads with building frontage
    (sizes, setbacks and gaps drawn from the ``buildings`` section's seeded ranges)."""
    spec = spec or {}
    cx.keys(spec, BUILDING_KEYS, "buildings")
    rng = np.random.default_rng(int(cx.num(spec, "seed", "buildings", default=0, lo=0)))
    setback = cx.rng(spec, "setback", "buildings", [1.0, 3.0])
    width = cx.rng(spec, "width", "buildings", [10.0, 20.0], lo=2.0)
    depth = cx.rng(spec, "depth", "buildings", [8.0, 14.0], lo=2.0)
    height = cx.rng(spec, "height", "buildings", [6.0, 20.0], lo=1.0)
    gap = cx.rng(spec, "gap", "buildings", [0.5, 4.0])
    fill = cx.num(spec, "fill", "buildings", default=0.85, lo=0.0, hi=1.0)
    out: list[Building] = []
    for k, b in enumerate(spec.get("list", []) or []):
        where = f"buildings.list[{k}]"
        cx.keys(b, {"x", "y", "w", "d", "yaw", "h", "facade"}, where)
        yaw = math.radians(cx.num(b, "yaw", where, default=0.0))
        fac = int(cx.num(b, "facade", where, default=0, lo=0, hi=len(style.facades) - 1))
        fp = rect(np.array([cx.num(b, "x", where), cx.num(b, "y", where)]),
                  np.array([math.cos(yaw), math.sin(yaw)]), cx.num(b, "w", where, lo=0.5),
                  cx.num(b, "d", where, lo=0.5))
        occ.take_poly(fp)
        out.append(Building(footprint=fp, height=cx.num(b, "h", where, lo=0.5), facade=fac))
    for road in roads:
        if frontage[road.id] != "buildings":
            continue
        for side in (-1.0, 1.0):  # right, left of the a->b direction
            s = 0.0
            while s < road.length:
                w = rng.uniform(*width)
                d = rng.uniform(*depth)
                off = hw + sw + rng.uniform(*setback)
                built = rng.random() < fill
                h = rng.uniform(*height)
                fac = int(rng.integers(len(style.facades)))
                if s + w > road.length:
                    break
                p, t, n = frames_at(road.centreline, np.array([s + w / 2]))
                n = n[0] * side
                fp = rect(p[0] + n * (off + d / 2), t[0], w, d)
                if polygon_area(fp) < 0:
                    fp = fp[::-1]
                if built and occ.free_poly(fp):
                    occ.take_poly(fp)
                    out.append(Building(footprint=fp, height=h, facade=fac))
                    s += w + rng.uniform(*gap)
                else:
                    s += 2.0 if built else w
    return out


def place_props(cx: FieldReader, spec: Any, roads: list[Road], frontage: dict, hw: float, sw: float,
                occ: Occupancy) -> list[Prop]:
    """The file's listed props, poles along every kerb, and trees behind the sidewalks wherever the lot is
    free (the ``props`` section's seeded spacing, sizes and fill)."""
    spec = spec or {}
    cx.keys(spec, PROP_KEYS, "props")
    rng = np.random.default_rng(int(cx.num(spec, "seed", "props", default=0, lo=0)))
    out: list[Prop] = []
    for k, p in enumerate(spec.get("list", []) or []):
        where = f"props.list[{k}]"
        cx.keys(p, {"kind", "x", "y", "h", "r"}, where)
        if p.get("kind") not in ("tree", "pole"):
            cx.fail(f"{where}.kind = {p.get('kind')!r}; accepted: tree, pole")
        out.append(Prop(kind=p["kind"], position=np.array([cx.num(p, "x", where), cx.num(p, "y", where)]),
                        height=cx.num(p, "h", where, lo=0.5), radius=cx.num(p, "r", where, lo=0.05)))
    trees = spec.get("trees", {}) or {}
    cx.keys(trees, {"spacing", "height", "radius", "fill"}, "props.trees")
    t_spacing = cx.rng(trees, "spacing", "props.trees", [8.0, 14.0], lo=1.0)
    t_height = cx.rng(trees, "height", "props.trees", [4.0, 8.0], lo=0.5)
    t_radius = cx.rng(trees, "radius", "props.trees", [1.2, 2.2], lo=0.2)
    t_fill = cx.num(trees, "fill", "props.trees", default=0.8, lo=0.0, hi=1.0)
    poles = spec.get("poles", {}) or {}
    cx.keys(poles, {"spacing", "height", "radius"}, "props.poles")
    p_spacing = cx.num(poles, "spacing", "props.poles", default=30.0, lo=0.0)
    p_height = cx.num(poles, "height", "props.poles", default=7.0, lo=0.5)
    p_radius = cx.num(poles, "radius", "props.poles", default=0.15, lo=0.02)
    for road in roads:
        for side in (-1.0, 1.0):
            # poles on the sidewalk near the kerb
            if p_spacing > 0 and sw > 0:
                for s in np.arange(p_spacing / 2, road.length - 2.0, p_spacing):
                    p, _, n = frames_at(road.centreline, np.array([s]))
                    out.append(Prop(kind="pole", position=p[0] + n[0] * side * (hw + 0.4),
                                    height=p_height, radius=p_radius))
            # trees behind the sidewalk wherever the lot is free (parks: roads with frontage trees)
            if frontage[road.id] == "none":
                continue
            s = rng.uniform(0.0, t_spacing[0])
            while s < road.length:
                r = rng.uniform(*t_radius)
                h = rng.uniform(*t_height)
                keep = rng.random() < t_fill
                p, _, n = frames_at(road.centreline, np.array([s]))
                c = p[0] + n[0] * side * (hw + sw + r + 1.0)
                if keep and occ.free_disc(c, r):
                    occ.take_disc(c, r)
                    out.append(Prop(kind="tree", position=c, height=h, radius=r))
                s += rng.uniform(*t_spacing)
    return out
