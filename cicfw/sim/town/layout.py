"""A town spec's road network, validated and built (``build_town``): nodes, roads trimmed at the junction
edges, junction polygons and bounds; then the buildings and props (``dressing``) and the ``Town``."""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from cicfw.sim.town.dressing import Occupancy, place_buildings, place_props
from cicfw.sim.town.fields import FRONTAGES, ROAD_KEYS, TOP_KEYS, FieldReader, read_style
from cicfw.sim.town.geometry import (STEP, left_normal, line_intersection, polygon_area, resample, rounded_polyline,
                                     trim_start, unit)
from cicfw.sim.town.model import Junction, Road, Town

MIN_ARM_ANGLE_DEG = 30.0  # two roads leaving one junction closer than this are rejected
MIN_ROAD_LENGTH = 6.0  # metres of road left between two junction edges


#: the largest town side (its nodes and roads plus ``margin`` on each side) a town file may give: the renderer
#: bakes the ground at 0.1 m a texel (about 1 GB of memory while baking town_a's 400 x 240 m)
MAX_TOWN_SIDE_M = 1000.0


def build_town(spec: Any, source: str = "<town>") -> Town:
    """Validate a parsed town spec (the YAML as a dict) and build its geometry."""
    cx = FieldReader(source)
    cx.keys(spec, TOP_KEYS, "town")
    name = spec.get("name")
    if not isinstance(name, str) or not name:
        cx.fail("town: missing field 'name' (a string)")
    lw = cx.num(spec, "lane_width", "town", lo=2.0, hi=6.0)
    sw = cx.num(spec, "sidewalk_width", "town", default=2.0, lo=0.0, hi=10.0)
    jr = cx.num(spec, "junction_radius", "town", default=10.0, lo=2.0, hi=50.0)
    margin = cx.num(spec, "margin", "town", default=30.0, lo=0.0)
    hw = lw  # half road width: one lane each way
    style = read_style(cx, spec.get("style"))

    nodes = _read_nodes(cx, spec)
    _check_extent(cx, np.array(list(nodes.values())), margin)  # before any road is resampled or grid allocated
    roads_in = _read_roads(cx, spec, nodes)
    arms = _junction_arms(cx, nodes, roads_in)
    _check_connected(cx, nodes, roads_in)
    full = _full_curves(cx, nodes, roads_in, jr)
    radius = _junction_radii(cx, arms, roads_in, full, jr, hw)  # and puts each junction's arms in CCW order
    _check_overlaps(cx, nodes, radius)
    roads = _trimmed_roads(cx, roads_in, full, nodes, radius)
    by_id = {r.id: r for r in roads}

    _check_crossings(cx, roads, hw)

    junctions = tuple(_junction(n, nodes[n], arms[n], by_id, hw, radius[n]) for n in sorted(nodes))

    # bounds
    allpts = np.vstack([r.centreline for r in roads] + [nodes[n][None] for n in nodes])
    _check_extent(cx, allpts, margin)  # curves (via points) may reach beyond the nodes
    lo, hi = allpts.min(axis=0) - margin, allpts.max(axis=0) + margin
    bounds = (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))

    occ = Occupancy(bounds, roads, junctions, hw, sw)
    frontage = {r["id"]: r["frontage"] for r in roads_in}
    buildings = place_buildings(cx, spec.get("buildings", {}), roads, frontage, hw, sw, occ, style)
    props = place_props(cx, spec.get("props", {}), roads, frontage, hw, sw, occ)

    return Town(name=name, lane_width=lw, sidewalk_width=sw, roads=tuple(roads), junctions=junctions,
                buildings=tuple(buildings), props=tuple(props), style=style, bounds=bounds,
                nodes=dict(nodes), source=source)


def _read_nodes(cx: FieldReader, spec: Any) -> dict[str, np.ndarray]:
    """The nodes (junction centres): node id -> position."""
    raw_nodes = spec.get("nodes")
    if not isinstance(raw_nodes, dict) or not raw_nodes:
        cx.fail("town: 'nodes' must be a mapping node_id: [x, y] with at least one node")
    return {str(k): cx.point(v, f"node {k!r}") for k, v in raw_nodes.items()}


def _read_roads(cx: FieldReader, spec: Any, nodes: dict) -> list[dict]:
    """The roads as the file gives them (full node-to-node, via points, radius, frontage), ids unique."""
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
    return roads_in


def _junction_arms(cx: FieldReader, nodes: dict, roads_in: list[dict]) -> dict[str, list[str]]:
    """Each node's roads; every node is a T (3) or X (4) junction."""
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
    return arms


def _check_connected(cx: FieldReader, nodes: dict, roads_in: list[dict]) -> None:
    """Every node reachable from the first one (roads are two-way)."""
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


def _full_curves(cx: FieldReader, nodes: dict, roads_in: list[dict], jr: float) -> dict[str, np.ndarray]:
    """Each road's centreline from node to node through its via points, corners rounded (0.25 m step)."""
    full: dict[str, np.ndarray] = {}
    for r in roads_in:
        pts = [nodes[r["a"]], *r["via"], nodes[r["b"]]]
        for k in range(len(pts) - 1):
            if np.linalg.norm(pts[k + 1] - pts[k]) < 1e-6:
                cx.fail(f"road {r['id']!r}: two consecutive points coincide at {pts[k].tolist()}")
        full[r["id"]] = resample(rounded_polyline(pts, r["radius"], jr + 2.0), STEP / 2)
    return full


def _junction_radii(cx: FieldReader, arms: dict[str, list[str]], roads_in: list[dict], full: dict, jr: float,
                    hw: float) -> dict[str, float]:
    """Each junction's radius (where its arms' centrelines start: wide enough for the sharpest pair of
    arms); reorders ``arms[n]`` counter-clockwise. Arms closer than MIN_ARM_ANGLE_DEG are an error."""
    radius: dict[str, float] = {}
    for n, lst in arms.items():
        dirs = []
        for rid in lst:
            r = next(x for x in roads_in if x["id"] == rid)
            curve = full[rid] if r["a"] == n else full[rid][::-1]
            d = unit(curve[min(4, len(curve) - 1)] - curve[0])
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
    return radius


def _check_overlaps(cx: FieldReader, nodes: dict, radius: dict[str, float]) -> None:
    """No two junctions closer than their radii plus MIN_ROAD_LENGTH of road."""
    names = sorted(nodes)
    for i, n1 in enumerate(names):
        for n2 in names[i + 1:]:
            d = float(np.linalg.norm(nodes[n1] - nodes[n2]))
            need = radius[n1] + radius[n2] + MIN_ROAD_LENGTH
            if d < need:
                cx.fail(f"junctions {n1!r} and {n2!r} overlap: their centres are {d:.1f} m apart, need "
                        f">= {need:.1f} m (junction radii {radius[n1]:.1f} + {radius[n2]:.1f} + "
                        f"{MIN_ROAD_LENGTH:.0f} m of road)")


def _trimmed_roads(cx: FieldReader, roads_in: list[dict], full: dict, nodes: dict,
                   radius: dict[str, float]) -> list[Road]:
    """Each road trimmed at both junction edges and resampled at STEP; at least MIN_ROAD_LENGTH long."""
    roads: list[Road] = []
    for r in roads_in:
        c, ok1 = trim_start(full[r["id"]], nodes[r["a"]], radius[r["a"]])
        c, ok2 = trim_start(c[::-1], nodes[r["b"]], radius[r["b"]])
        c = c[::-1]
        length = float(np.sum(np.linalg.norm(np.diff(c, axis=0), axis=1))) if len(c) > 1 else 0.0
        if not (ok1 and ok2) or length < MIN_ROAD_LENGTH:
            cx.fail(f"road {r['id']!r} is too short: {length:.1f} m left between the junctions "
                    f"(need >= {MIN_ROAD_LENGTH:.0f} m)")
        c = resample(c, STEP)
        roads.append(Road(id=r["id"], a=r["a"], b=r["b"], centreline=c, length=length))
    return roads


def _check_extent(cx: FieldReader, pts: np.ndarray, margin: float) -> None:
    """One clear error when the town (its points plus ``margin`` on each side) is more than
    MAX_TOWN_SIDE_M a side: its occupancy grid and ground texture would not fit in memory."""
    span = pts.max(axis=0) - pts.min(axis=0)
    side = span + 2 * margin
    if float(side.max()) > MAX_TOWN_SIDE_M:
        cx.fail(f"town: the town spans {side[0]:.0f} x {side[1]:.0f} m (its nodes and roads {span[0]:.0f} x "
                f"{span[1]:.0f} m plus margin {margin:g} m on each side); at most {MAX_TOWN_SIDE_M:g} m a side is "
                f"accepted (the renderer bakes the ground at 0.1 m a texel, ~1 GB for the shipped 400 x 240 m "
                f"town_a): lower 'margin' (the shipped towns use 35 m) or bring the nodes closer")


def _check_crossings(cx: FieldReader, roads: list[Road], hw: float) -> None:
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
            e, t = r.centreline[0], unit(r.centreline[1] - r.centreline[0])
        else:
            e, t = r.centreline[-1], unit(r.centreline[-2] - r.centreline[-1])
        lft = left_normal(t)
        mouths.append((e - hw * lft, e + hw * lft, t))  # (clockwise edge, counter-clockwise edge, outward)
    poly = []
    for k, (pr, pl, t) in enumerate(mouths):
        poly += [pr, pl]
        nr, _, nt = mouths[(k + 1) % len(mouths)]
        ctrl = line_intersection(pl, t, nr, nt)
        if ctrl is not None and np.dot(ctrl - pl, t) < 0 and np.dot(ctrl - nr, nt) < 0:
            s = np.linspace(0, 1, 9)[1:-1, None]
            poly += list((1 - s) ** 2 * pl + 2 * s * (1 - s) * ctrl + s ** 2 * nr)
    poly = np.array(poly)
    if polygon_area(poly) < 0:
        poly = poly[::-1]
    return Junction(id=n, centre=c.copy(), polygon=poly, arms=tuple(arm_ids), radius=radius)
