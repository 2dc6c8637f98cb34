"""Towns as data: load a town YAML file (``conf/town/<name>.yaml``), validate it, build its geometry.

A town file lists nodes (junction centres), two-way roads between them (optionally bent through
``via`` points with rounded corners), the lane and sidewalk widths, a style, and compact rules that
generate buildings and props deterministically from a seed. ``load_town`` returns a ``Town`` (see
``/work/notes/TOWN_CONTRACT.md`` and docs/simulator.md); any mistake in the file raises one
``TownError`` naming the element. Coordinates: metres, x east, y north, yaw CCW from +x.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

STEP = 0.5  # metres between centreline samples
MIN_ARM_ANGLE_DEG = 30.0  # two roads leaving one junction closer than this are rejected
MIN_ROAD_LENGTH = 6.0  # metres of road left between two junction edges


#: the largest town side (its nodes and roads plus ``margin`` on each side) a town file may give: the renderer
#: bakes the ground at 0.1 m a texel (about 1 GB of memory while baking town_a's 400 x 240 m)
MAX_TOWN_SIDE_M = 1000.0


class TownError(ValueError):
    """A town file that cannot be built; the message names the file, the element and the fix."""


# ----------------------------------------------------------------------------------------------
# The Town object (the contract with the renderer)


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


# ----------------------------------------------------------------------------------------------
# Finding and reading town files

TOP_KEYS = {
    "name", "lane_width", "sidewalk_width", "junction_radius", "margin", "style",
    "nodes", "roads", "buildings", "props",
}
STYLE_KEYS = ("road", "marking", "centre_line", "sidewalk", "terrain", "facades", "roof",
              "vegetation", "pole", "sky")
ROAD_KEYS = {"id", "a", "b", "via", "radius", "frontage"}
FRONTAGES = ("buildings", "trees", "none")
BUILDING_KEYS = {"seed", "setback", "width", "depth", "height", "gap", "fill", "list"}
PROP_KEYS = {"seed", "trees", "poles", "list"}


def _town_dir():
    return resources.files("cicfw.conf") / "town"


def town_names() -> list[str]:
    """Names of the shipped towns (``conf/town/*.yaml``)."""
    return sorted(p.name[:-5] for p in _town_dir().iterdir() if p.name.endswith(".yaml"))


def town_path(name_or_path: str | Path) -> Path:
    """The YAML file of a shipped town name, or the given path; error naming the known towns."""
    s = str(name_or_path)
    if s.endswith((".yaml", ".yml")) or "/" in s or "\\" in s:
        p = Path(s).expanduser()
        if not p.is_file():
            raise TownError(f"town file {s!r} does not exist")
        return p.resolve()
    p = _town_dir() / f"{s}.yaml"
    if not p.is_file():
        raise TownError(
            f"unknown town {s!r}; shipped towns: {', '.join(town_names())} "
            f"(or give a path to a town .yaml file)"
        )
    return Path(str(p)).resolve()


def load_town(name_or_path: str | Path) -> Town:
    """Load, validate and build a town: ``"town_a"``, ``"town_b"`` or a path to a YAML file."""
    p = town_path(name_or_path)
    return _load_cached(str(p), p.stat().st_mtime_ns)


@functools.lru_cache(maxsize=16)
def _load_cached(path: str, _mtime: int) -> Town:
    try:
        spec = yaml.safe_load(Path(path).read_text())
    except yaml.YAMLError as err:
        raise TownError(f"{path}: not valid YAML ({err})") from None
    return build_town(spec, source=path)


# ----------------------------------------------------------------------------------------------
# Field checks (one clear error each)


class _Ctx:
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


# ----------------------------------------------------------------------------------------------
# Geometry helpers


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v)
    return v / n if n > 0 else v


def _left(v: np.ndarray) -> np.ndarray:
    return np.array([-v[1], v[0]])


def resample(poly: np.ndarray, step: float = STEP) -> np.ndarray:
    """Resample a polyline at (about) ``step`` metres, keeping both end points."""
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    keep = np.concatenate([[True], seg > 1e-9])
    poly, s = poly[keep], np.concatenate([[0.0], np.cumsum(seg[seg > 1e-9])])
    n = max(int(math.ceil(s[-1] / step)), 1)
    t = np.linspace(0.0, s[-1], n + 1)
    return np.stack([np.interp(t, s, poly[:, 0]), np.interp(t, s, poly[:, 1])], axis=1)


def _rounded_polyline(pts: list, radius: float, end_keep: float) -> np.ndarray:
    """A polyline through ``pts`` with each interior corner rounded by an arc of ``radius`` (or less
    where the segments are short; the end segments keep ``end_keep`` metres straight)."""
    out = [pts[0]]
    n = len(pts)
    for i in range(1, n - 1):
        p0, p1, p2 = pts[i - 1], pts[i], pts[i + 1]
        u1, u2 = _unit(p1 - p0), _unit(p2 - p1)
        cross = u1[0] * u2[1] - u1[1] * u2[0]
        phi = math.atan2(abs(cross), float(np.dot(u1, u2)))  # turn angle
        if phi < 1e-3:
            out.append(p1)
            continue
        l_in, l_out = np.linalg.norm(p1 - p0), np.linalg.norm(p2 - p1)
        lim_in = l_in - end_keep if i == 1 else 0.5 * l_in
        lim_out = l_out - end_keep if i == n - 2 else 0.5 * l_out
        t = min(radius * math.tan(phi / 2), max(lim_in, 0.0), max(lim_out, 0.0))
        r = t / math.tan(phi / 2)
        a0 = p1 - u1 * t
        sign = 1.0 if cross > 0 else -1.0  # left turn: centre on the left
        c = a0 + sign * _left(u1) * r
        ang0 = math.atan2(*(a0 - c)[::-1])
        k = max(int(math.ceil(r * phi / 0.1)), 2)
        angs = ang0 + sign * np.linspace(0.0, phi, k + 1)
        out.extend(c + r * np.stack([np.cos(angs), np.sin(angs)], axis=1))
    out.append(pts[-1])
    return np.vstack(out)


def _cut(poly: np.ndarray, centre: np.ndarray, radius: float) -> tuple[np.ndarray, bool]:
    """Drop the start of ``poly`` inside the circle (centre, radius); the new start lies on the circle."""
    d = np.linalg.norm(poly - centre, axis=1)
    out = np.nonzero(d >= radius)[0]
    if len(out) == 0:
        return poly[-1:], False
    i = int(out[0])
    if i == 0:
        return poly, True
    p, q = poly[i - 1], poly[i]
    # solve |p + t (q - p) - c| = radius for t in [0, 1]
    dvec, f = q - p, p - centre
    a, b, cc = dvec @ dvec, 2 * f @ dvec, f @ f - radius * radius
    disc = max(b * b - 4 * a * cc, 0.0)
    t = (-b + math.sqrt(disc)) / (2 * a)
    start = p + np.clip(t, 0.0, 1.0) * dvec
    return np.vstack([start, poly[i:]]), True


def _line_intersection(p: np.ndarray, u: np.ndarray, q: np.ndarray, v: np.ndarray) -> np.ndarray | None:
    den = u[0] * v[1] - u[1] * v[0]
    if abs(den) < 1e-6:
        return None
    t = ((q[0] - p[0]) * v[1] - (q[1] - p[1]) * v[0]) / den
    return p + t * u


def _polygon_area(poly: np.ndarray) -> float:
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def _rect(centre: np.ndarray, along: np.ndarray, w: float, d: float) -> np.ndarray:
    """CCW rectangle of width ``w`` along unit ``along`` and depth ``d`` across it."""
    ac = _left(along)
    hw, hd = along * (w / 2), ac * (d / 2)
    return np.array([centre - hw - hd, centre + hw - hd, centre + hw + hd, centre - hw + hd])


# ----------------------------------------------------------------------------------------------
# Building a town from its spec


def build_town(spec: Any, source: str = "<town>") -> Town:
    """Validate a parsed town spec (the YAML as a dict) and build its geometry."""
    cx = _Ctx(source)
    cx.keys(spec, TOP_KEYS, "town")
    name = spec.get("name")
    if not isinstance(name, str) or not name:
        cx.fail("town: missing field 'name' (a string)")
    lw = cx.num(spec, "lane_width", "town", lo=2.0, hi=6.0)
    sw = cx.num(spec, "sidewalk_width", "town", default=2.0, lo=0.0, hi=10.0)
    jr = cx.num(spec, "junction_radius", "town", default=10.0, lo=2.0, hi=50.0)
    margin = cx.num(spec, "margin", "town", default=30.0, lo=0.0)
    hw = lw  # half road width: one lane each way
    style = _style(cx, spec.get("style"))

    # nodes
    raw_nodes = spec.get("nodes")
    if not isinstance(raw_nodes, dict) or not raw_nodes:
        cx.fail("town: 'nodes' must be a mapping node_id: [x, y] with at least one node")
    nodes = {str(k): cx.point(v, f"node {k!r}") for k, v in raw_nodes.items()}
    _check_extent(cx, np.array(list(nodes.values())), margin)  # before any road is resampled or grid allocated

    # roads: full node-to-node curves first
    raw_roads = spec.get("roads")
    if not isinstance(raw_roads, list) or not raw_roads:
        cx.fail("town: 'roads' must be a list of roads ([a, b] or {a:, b:, via:, radius:, frontage:})")
    roads_in: list[dict] = []
    for i, r in enumerate(raw_roads):
        where = f"road #{i}"
        if isinstance(r, (list, tuple)):
            if len(r) != 2:
                cx.fail(f"{where} {r!r}: a road is [a, b] (two node ids) or a mapping with a: and b:")
            r = {"a": r[0], "b": r[1]}
        cx.keys(r, ROAD_KEYS, where)
        a, b = r.get("a"), r.get("b")
        rid = str(r.get("id", f"{a}-{b}"))
        where = f"road {rid!r}"
        for end in (a, b):
            if end is None:
                cx.fail(f"{where}: needs both ends 'a' and 'b' (node ids)")
            if str(end) not in nodes:
                cx.fail(f"{where}: dangling road, end {end!r} is not a node (unknown node); "
                        f"nodes: {', '.join(sorted(nodes))}")
        a, b = str(a), str(b)
        if a == b:
            cx.fail(f"{where}: both ends are node {a!r}; a road joins two different nodes")
        via = r.get("via", [])
        if not isinstance(via, list):
            cx.fail(f"{where}.via must be a list of points [[x, y], ...]")
        via = [cx.point(v, f"{where}.via[{k}]") for k, v in enumerate(via)]
        frontage = r.get("frontage", "buildings")
        if frontage not in FRONTAGES:
            cx.fail(f"{where}.frontage = {frontage!r}; accepted: {', '.join(FRONTAGES)}")
        roads_in.append(dict(id=rid, a=a, b=b, via=via, frontage=frontage,
                             radius=cx.num(r, "radius", where, default=25.0, lo=1.0)))
    ids = [r["id"] for r in roads_in]
    dup = sorted({x for x in ids if ids.count(x) > 1})
    if dup:
        cx.fail(f"road {dup[0]!r} is defined twice; give one of them an 'id:'")

    # degrees: T (3) and X (4) junctions only
    arms: dict[str, list[str]] = {n: [] for n in nodes}
    for r in roads_in:
        arms[r["a"]].append(r["id"])
        arms[r["b"]].append(r["id"])
    for n, lst in arms.items():
        if len(lst) == 0:
            cx.fail(f"node {n!r} has no road (isolated component); remove it or connect it")
        if len(lst) == 1:
            cx.fail(f"node {n!r} is a dead end (only road {lst[0]!r}); every node must be a T (3 roads) "
                    f"or X (4 roads) junction")
        if len(lst) == 2:
            cx.fail(f"node {n!r} joins only 2 roads ({', '.join(lst)}); a bend is one road with 'via:' "
                    f"points, a node is a T (3 roads) or X (4 roads) junction")
        if len(lst) > 4:
            cx.fail(f"node {n!r} joins {len(lst)} roads; junctions are T (3) or X (4)")

    # connectivity (undirected)
    seen, todo = set(), [next(iter(nodes))]
    nbr: dict[str, set] = {n: set() for n in nodes}
    for r in roads_in:
        nbr[r["a"]].add(r["b"])
        nbr[r["b"]].add(r["a"])
    while todo:
        n = todo.pop()
        if n not in seen:
            seen.add(n)
            todo.extend(nbr[n] - seen)
    if len(seen) != len(nodes):
        lost = sorted(set(nodes) - seen)
        cx.fail(f"node {lost[0]!r} is in an isolated component: it cannot be reached from node "
                f"{next(iter(nodes))!r} (unreachable: {', '.join(lost)})")

    # full curves, arm directions and junction radii
    full: dict[str, np.ndarray] = {}
    for r in roads_in:
        pts = [nodes[r["a"]], *r["via"], nodes[r["b"]]]
        for k in range(len(pts) - 1):
            if np.linalg.norm(pts[k + 1] - pts[k]) < 1e-6:
                cx.fail(f"road {r['id']!r}: two consecutive points coincide at {pts[k].tolist()}")
        full[r["id"]] = resample(_rounded_polyline(pts, r["radius"], jr + 2.0), STEP / 2)
    radius: dict[str, float] = {}
    arm_dir: dict[tuple, np.ndarray] = {}
    for n, lst in arms.items():
        dirs = []
        for rid in lst:
            r = next(x for x in roads_in if x["id"] == rid)
            curve = full[rid] if r["a"] == n else full[rid][::-1]
            d = _unit(curve[min(4, len(curve) - 1)] - curve[0])
            arm_dir[(n, rid)] = d
            dirs.append((math.atan2(d[1], d[0]), rid))
        dirs.sort()
        need = jr
        for k in range(len(dirs)):
            a1, r1 = dirs[k]
            a2, r2 = dirs[(k + 1) % len(dirs)]
            gap = (a2 - a1) % (2 * math.pi)
            if math.degrees(gap) < MIN_ARM_ANGLE_DEG:
                cx.fail(f"roads {r1!r} and {r2!r} leave junction {n!r} {math.degrees(gap):.0f} deg apart; "
                        f"they must be at least {MIN_ARM_ANGLE_DEG:.0f} deg apart")
            if gap < math.pi:
                need = max(need, hw / math.tan(gap / 2) + 2.0)
        radius[n] = need
        arms[n] = [rid for _, rid in dirs]  # CCW order

    # overlapping junctions
    names = sorted(nodes)
    for i, n1 in enumerate(names):
        for n2 in names[i + 1:]:
            d = float(np.linalg.norm(nodes[n1] - nodes[n2]))
            need = radius[n1] + radius[n2] + MIN_ROAD_LENGTH
            if d < need:
                cx.fail(f"junctions {n1!r} and {n2!r} overlap: their centres are {d:.1f} m apart, need "
                        f">= {need:.1f} m (junction radii {radius[n1]:.1f} + {radius[n2]:.1f} + "
                        f"{MIN_ROAD_LENGTH:.0f} m of road)")

    # trim each road at both junction edges
    roads: list[Road] = []
    for r in roads_in:
        c, ok1 = _cut(full[r["id"]], nodes[r["a"]], radius[r["a"]])
        c, ok2 = _cut(c[::-1], nodes[r["b"]], radius[r["b"]])
        c = c[::-1]
        length = float(np.sum(np.linalg.norm(np.diff(c, axis=0), axis=1))) if len(c) > 1 else 0.0
        if not (ok1 and ok2) or length < MIN_ROAD_LENGTH:
            cx.fail(f"road {r['id']!r} is too short: {length:.1f} m left between the junctions "
                    f"(need >= {MIN_ROAD_LENGTH:.0f} m)")
        c = resample(c, STEP)
        roads.append(Road(id=r["id"], a=r["a"], b=r["b"], centreline=c, length=length))
    by_id = {r.id: r for r in roads}

    _check_crossings(cx, roads, hw)

    junctions = tuple(_junction(n, nodes[n], arms[n], by_id, hw, radius[n]) for n in sorted(nodes))

    # bounds
    allpts = np.vstack([r.centreline for r in roads] + [nodes[n][None] for n in nodes])
    _check_extent(cx, allpts, margin)  # curves (via points) may reach beyond the nodes
    lo, hi = allpts.min(axis=0) - margin, allpts.max(axis=0) + margin
    bounds = (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))

    occ = _Occupancy(bounds, roads, junctions, hw, sw)
    frontage = {r["id"]: r["frontage"] for r in roads_in}
    buildings = _buildings(cx, spec.get("buildings", {}), roads, frontage, hw, sw, occ, style)
    props = _props(cx, spec.get("props", {}), roads, frontage, hw, sw, occ)

    return Town(name=name, lane_width=lw, sidewalk_width=sw, roads=tuple(roads), junctions=junctions,
                buildings=tuple(buildings), props=tuple(props), style=style, bounds=bounds,
                nodes=dict(nodes), source=source)


def _check_extent(cx: _Ctx, pts: np.ndarray, margin: float) -> None:
    """One clear error when the town (its points plus ``margin`` on each side) is more than
    MAX_TOWN_SIDE_M a side: its occupancy grid and ground texture would not fit in memory."""
    span = pts.max(axis=0) - pts.min(axis=0)
    side = span + 2 * margin
    if float(side.max()) > MAX_TOWN_SIDE_M:
        cx.fail(f"town: the town spans {side[0]:.0f} x {side[1]:.0f} m (its nodes and roads {span[0]:.0f} x "
                f"{span[1]:.0f} m plus margin {margin:g} m on each side); at most {MAX_TOWN_SIDE_M:g} m a side is "
                f"accepted (the renderer bakes the ground at 0.1 m a texel, ~1 GB for the shipped 400 x 240 m "
                f"town_a): lower 'margin' (the shipped towns use 35 m) or bring the nodes closer")


def _style(cx: _Ctx, s: Any) -> Style:
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


def _check_crossings(cx: _Ctx, roads: list[Road], hw: float) -> None:
    """Two roads whose paved surfaces touch outside a junction cross without a node: reject."""
    boxes = [(r.centreline.min(0) - 2 * hw, r.centreline.max(0) + 2 * hw) for r in roads]
    for i, r1 in enumerate(roads):
        for j in range(i + 1, len(roads)):
            r2 = roads[j]
            if np.any(boxes[i][1] < boxes[j][0]) or np.any(boxes[j][1] < boxes[i][0]):
                continue
            p, q = r1.centreline[::2], r2.centreline[::2]
            d = np.sqrt(((p[:, None, :] - q[None, :, :]) ** 2).sum(-1)).min()
            if d < 2 * hw:
                cx.fail(f"roads {r1.id!r} and {r2.id!r} cross or overlap outside a junction "
                        f"(closest {d:.1f} m); add a node where they meet or move them apart")


def _junction(n: str, c: np.ndarray, arm_ids: list[str], by_id: dict, hw: float, radius: float) -> Junction:
    """Paved polygon: each arm's mouth (its road edge points) joined by rounded curb corners."""
    mouths = []
    for rid in arm_ids:  # already CCW
        r = by_id[rid]
        if r.a == n:
            e, t = r.centreline[0], _unit(r.centreline[1] - r.centreline[0])
        else:
            e, t = r.centreline[-1], _unit(r.centreline[-2] - r.centreline[-1])
        lft = _left(t)
        mouths.append((e - hw * lft, e + hw * lft, t))  # (clockwise edge, counter-clockwise edge, outward)
    poly = []
    for k, (pr, pl, t) in enumerate(mouths):
        poly += [pr, pl]
        nr, _, nt = mouths[(k + 1) % len(mouths)]
        ctrl = _line_intersection(pl, t, nr, nt)
        if ctrl is not None and np.dot(ctrl - pl, t) < 0 and np.dot(ctrl - nr, nt) < 0:
            s = np.linspace(0, 1, 9)[1:-1, None]
            poly += list((1 - s) ** 2 * pl + 2 * s * (1 - s) * ctrl + s ** 2 * nr)
    poly = np.array(poly)
    if _polygon_area(poly) < 0:
        poly = poly[::-1]
    return Junction(id=n, centre=c.copy(), polygon=poly, arms=tuple(arm_ids), radius=radius)


class _Occupancy:
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
        return self.free_poly(_rect(c, np.array([1.0, 0.0]), 2 * r, 2 * r))

    def take_disc(self, c: np.ndarray, r: float) -> None:
        cv2.circle(self.grid, tuple(int(v) for v in self.px(c[None])[0, 0]), int(math.ceil(r / self.RES)), 1, -1)


def _frames(road: Road, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points and unit tangents of ``road`` at arc lengths ``s``."""
    c = road.centreline
    seg = np.linalg.norm(np.diff(c, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    p = np.stack([np.interp(s, cum, c[:, 0]), np.interp(s, cum, c[:, 1])], axis=1)
    i = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(c) - 2)
    t = c[i + 1] - c[i]
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    return p, t


def _buildings(cx: _Ctx, spec: Any, roads: list[Road], frontage: dict, hw: float, sw: float,
               occ: _Occupancy, style: Style) -> list[Building]:
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
        fp = _rect(np.array([cx.num(b, "x", where), cx.num(b, "y", where)]),
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
                p, t = _frames(road, np.array([s + w / 2]))
                n = _left(t[0]) * side
                fp = _rect(p[0] + n * (off + d / 2), t[0], w, d)
                if _polygon_area(fp) < 0:
                    fp = fp[::-1]
                if built and occ.free_poly(fp):
                    occ.take_poly(fp)
                    out.append(Building(footprint=fp, height=h, facade=fac))
                    s += w + rng.uniform(*gap)
                else:
                    s += 2.0 if built else w
    return out


def _props(cx: _Ctx, spec: Any, roads: list[Road], frontage: dict, hw: float, sw: float,
           occ: _Occupancy) -> list[Prop]:
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
                    p, t = _frames(road, np.array([s]))
                    out.append(Prop(kind="pole", position=p[0] + _left(t[0]) * side * (hw + 0.4),
                                    height=p_height, radius=p_radius))
            # trees behind the sidewalk wherever the lot is free (parks: roads with frontage trees)
            if frontage[road.id] == "none":
                continue
            s = rng.uniform(0.0, t_spacing[0])
            while s < road.length:
                r = rng.uniform(*t_radius)
                h = rng.uniform(*t_height)
                keep = rng.random() < t_fill
                p, t = _frames(road, np.array([s]))
                c = p[0] + _left(t[0]) * side * (hw + sw + r + 1.0)
                if keep and occ.free_disc(c, r):
                    occ.take_disc(c, r)
                    out.append(Prop(kind="tree", position=c, height=h, radius=r))
                s += rng.uniform(*t_spacing)
    return out
