"""Lane-level road graph, router and routes with the high-level command at every point.

Each road has two directed lanes, ``lane_width/2`` right of its centreline (right-hand traffic).
At a junction every incoming lane is joined to the outgoing lane of every *other* arm (no U-turns)
by a cubic Bezier connector classified left / right / straight. A ``Route`` is a dense polyline
(0.5 m step) with, at every point, the CIL command: the turn's code from ``command_distance`` metres
before a junction until its exit, follow lane (2) elsewhere.
"""
from __future__ import annotations

import functools
import heapq
import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from cicfw.sim.town import STEP, Town, TownError, resample

FOLLOW, LEFT, RIGHT, STRAIGHT = 2, 3, 4, 5  # CIL command codes (branch = code - 2)
COMMAND_NAMES = {FOLLOW: "follow", LEFT: "left", RIGHT: "right", STRAIGHT: "straight"}
COMMAND_DISTANCE = 12.0  # metres before a junction's entry where its turn command starts
STRAIGHT_MAX_DEG = 45.0  # |heading change| through a junction below this is "straight"


@dataclass(frozen=True, eq=False)
class Lane:
    """One direction of a road: ``points`` from ``start`` node's junction edge to ``end`` node's."""

    id: str  # "<road>:+" (a -> b) or "<road>:-" (b -> a)
    road: str
    start: str
    end: str
    points: np.ndarray
    length: float


@dataclass(frozen=True, eq=False)
class Connector:
    """A path through junction ``junction`` from lane ``src``'s end to lane ``dst``'s start."""

    junction: str
    src: str
    dst: str
    command: int  # LEFT, RIGHT or STRAIGHT
    points: np.ndarray
    length: float


@dataclass(eq=False)
class Route:
    """A planned route: dense points with heading, arc length, curvature and command at each point."""

    name: str
    points: np.ndarray  # (N, 2)
    heading: np.ndarray  # (N,) rad
    s: np.ndarray  # (N,) arc length from the start
    curvature: np.ndarray  # (N,) 1/m, positive = turning left
    commands: np.ndarray  # (N,) int8 CIL codes
    in_junction: np.ndarray  # (N,) bool
    lanes: tuple  # lane ids driven, in order
    turns: tuple  # ((junction, command, s_entry, s_exit), ...)
    meta: dict = field(default_factory=dict)

    @property
    def length(self) -> float:
        return float(self.s[-1])

    @property
    def start_pose(self) -> tuple[float, float, float]:
        return float(self.points[0, 0]), float(self.points[0, 1]), float(self.heading[0])

    @property
    def goal(self) -> np.ndarray:
        return self.points[-1]

    def timeout(self, speed_kmh: float = 10.0, extra_s: float = 10.0) -> float:
        """The CoRL-2017 time budget: the route length at ``speed_kmh`` plus ``extra_s`` seconds."""
        return self.length / (speed_kmh / 3.6) + extra_s


def _cum(poly: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poly, axis=0), axis=1))])


def _slice(poly: np.ndarray, s0: float, s1: float) -> np.ndarray:
    """The part of ``poly`` between arc lengths s0 < s1 (interpolated ends)."""
    cum = _cum(poly)
    s0, s1 = max(s0, 0.0), min(s1, cum[-1])
    inner = (cum > s0) & (cum < s1)
    ends = [np.array([[np.interp(s, cum, poly[:, 0]), np.interp(s, cum, poly[:, 1])]]) for s in (s0, s1)]
    return np.vstack([ends[0], poly[inner], ends[1]])


def _heading(poly: np.ndarray) -> np.ndarray:
    d = np.gradient(poly, axis=0)
    return np.arctan2(d[:, 1], d[:, 0])


def turn_code(change_deg: float) -> int:
    """CIL command of a manoeuvre with this heading change (degrees, positive = left)."""
    if abs(change_deg) < STRAIGHT_MAX_DEG:
        return STRAIGHT
    return LEFT if change_deg > 0 else RIGHT


def turn_commands(s: np.ndarray, turns: Sequence[tuple], command_distance: float) -> tuple[np.ndarray, np.ndarray]:
    """Each route point's command and whether it lies in a junction, from its arc length ``s`` and the route's
    ``turns`` ``(junction, command, entry, exit)`` (m): a turn's command from ``command_distance`` before its
    entry to its exit, follow elsewhere."""
    commands, in_j = np.full(len(s), FOLLOW, np.int8), np.zeros(len(s), bool)
    for _, cmd, entry, exit_ in turns:
        commands[(s >= entry - command_distance) & (s <= exit_)] = cmd
        in_j[(s >= entry) & (s <= exit_)] = True
    return commands, in_j


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def _bezier(p0, h0, p1, h1, n: int = 48) -> np.ndarray:
    """Cubic Bezier leaving p0 along heading h0 and arriving at p1 along h1; handles sized so a
    circular-arc-like turn results (4/3 tan(phi/4) R)."""
    phi = abs(_wrap(h1 - h0))
    dist = float(np.linalg.norm(p1 - p0))
    if phi < 1e-3:
        k = dist / 3
    else:
        radius = dist / (2 * math.sin(phi / 2))
        k = 4 / 3 * math.tan(phi / 4) * radius
    c0 = p0 + k * np.array([math.cos(h0), math.sin(h0)])
    c1 = p1 - k * np.array([math.cos(h1), math.sin(h1)])
    t = np.linspace(0, 1, n)[:, None]
    return (1 - t) ** 3 * p0 + 3 * (1 - t) ** 2 * t * c0 + 3 * (1 - t) * t ** 2 * c1 + t ** 3 * p1


class RoadGraph:
    """Lanes and junction connectors of a town, with Dijkstra routing between lanes and poses."""

    def __init__(self, town: Town, command_distance: float = COMMAND_DISTANCE) -> None:
        self.town = town
        self.command_distance = command_distance
        half = town.lane_width / 2
        self.lanes: dict[str, Lane] = {}
        for r in town.roads:
            for sign, pts, start, end in ((+1, r.centreline, r.a, r.b), (-1, r.centreline[::-1], r.b, r.a)):
                t = np.gradient(pts, axis=0)
                t /= np.linalg.norm(t, axis=1, keepdims=True)
                right = np.stack([t[:, 1], -t[:, 0]], axis=1)
                lp = resample(pts + right * half, STEP)
                lid = f"{r.id}:{'+' if sign > 0 else '-'}"
                self.lanes[lid] = Lane(lid, r.id, start, end, lp, float(_cum(lp)[-1]))
        self.connectors: dict[tuple[str, str], Connector] = {}
        self.out: dict[str, list[str]] = {lid: [] for lid in self.lanes}
        for j in town.junctions:
            ins = [lane for lane in self.lanes.values() if lane.end == j.id]
            outs = [lane for lane in self.lanes.values() if lane.start == j.id]
            for li in ins:
                exits = [lo for lo in outs if lo.road != li.road]
                h_in = float(_heading(li.points)[-1])
                turns = sorted((float(_wrap(_heading(lo.points)[0] - h_in)), lo.id) for lo in exits)
                cmds = self._classify(j.id, li, [a for a, _ in turns])
                for (ang, lo_id), cmd in zip(turns, cmds):
                    lo = self.lanes[lo_id]
                    pts = _bezier(li.points[-1], h_in, lo.points[0], float(_heading(lo.points)[0]))
                    self.connectors[(li.id, lo.id)] = Connector(j.id, li.id, lo.id, cmd, pts,
                                                                float(_cum(pts)[-1]))
                    self.out[li.id].append(lo.id)
        self._check_strongly_connected()
        # flat arrays of every lane point, for locating poses
        ids = sorted(self.lanes)
        self._lane_ids = ids
        self._pts = np.vstack([self.lanes[i].points for i in ids])
        self._pt_lane = np.concatenate([np.full(len(self.lanes[i].points), k) for k, i in enumerate(ids)])
        self._pt_s = np.concatenate([_cum(self.lanes[i].points) for i in ids])
        self._pt_h = np.concatenate([_heading(self.lanes[i].points) for i in ids])

    def _classify(self, jid: str, lane: Lane, angles: list[float]) -> list[int]:
        """Commands for the exits of one incoming lane, sorted by heading change (right to left)."""
        if len(angles) == 3:  # X: rightmost right, middle straight, leftmost left
            return [RIGHT, STRAIGHT, LEFT]
        cmds = [turn_code(math.degrees(a)) for a in angles]
        if len(set(cmds)) != len(cmds):
            raise TownError(
                f"{self.town.source}: junction {jid!r}: arriving on road {lane.road!r}, two exits would both "
                f"be {COMMAND_NAMES[cmds[0]]!r} (heading changes "
                f"{', '.join(f'{math.degrees(a):.0f}' for a in angles)} deg); move the arms so one exit is "
                f"straight (< {STRAIGHT_MAX_DEG:.0f} deg) or they turn opposite ways"
            )
        return cmds

    def _check_strongly_connected(self) -> None:
        first = sorted(self.lanes)[0]
        back: dict[str, list[str]] = {lid: [] for lid in self.lanes}
        for a, bs in self.out.items():
            for b in bs:
                back[b].append(a)
        for adj, word in ((self.out, "reached from"), (back, "reach")):
            seen, todo = set(), [first]
            while todo:
                x = todo.pop()
                if x not in seen:
                    seen.add(x)
                    todo.extend(adj[x])
            if len(seen) != len(self.lanes):
                bad = sorted(set(self.lanes) - seen)[0]
                raise TownError(f"{self.town.source}: lane {bad!r} cannot be {word} lane {first!r} "
                                f"(no U-turns): the road network must let every lane reach every other")

    # ------------------------------------------------------------------------------------------
    # locating and routing

    def locate(self, x: float, y: float, yaw: float | None = None) -> tuple[str, float, float]:
        """Nearest lane point (lane id, arc length, distance); with ``yaw``, only lanes heading within 90 deg."""
        d2 = (self._pts[:, 0] - x) ** 2 + (self._pts[:, 1] - y) ** 2
        if yaw is not None:
            d2 = d2 + 1e6 * (np.cos(self._pt_h - yaw) < 0.0)
        i = int(np.argmin(d2))
        return self._lane_ids[self._pt_lane[i]], float(self._pt_s[i]), float(math.sqrt(d2[i] % 1e6))

    def shortest_lanes(self, src: str, dst: str) -> list[str]:
        """Lane ids from ``src`` to ``dst`` minimising the driven length (src == dst -> [src])."""
        if src == dst:
            return [src]
        dist = {src: 0.0}
        prev: dict[str, str] = {}
        heap = [(0.0, src)]
        while heap:
            d, x = heapq.heappop(heap)
            if x == dst:
                break
            if d > dist.get(x, math.inf):
                continue
            for y in self.out[x]:
                nd = d + self.connectors[(x, y)].length + self.lanes[y].length
                if nd < dist.get(y, math.inf):
                    dist[y], prev[y] = nd, x
                    heapq.heappush(heap, (nd, y))
        path = [dst]
        while path[-1] != src:
            path.append(prev[path[-1]])
        return path[::-1]

    def route(self, start: tuple[float, float, float], goal: tuple[float, float, float] | tuple[float, float],
              name: str = "route") -> Route:
        """Shortest route from a start pose (x, y, yaw) to a goal (x, y[, yaw]) along lanes."""
        l0, s0, _ = self.locate(*start)
        l1, s1, _ = self.locate(*goal) if len(goal) == 3 else self.locate(goal[0], goal[1])
        if l0 == l1 and s1 > s0:
            lanes = [l0]
        else:
            # leave l0, come back round to l1 (also when the goal is behind on the same lane)
            best = None
            for nxt in self.out[l0]:
                path = [l0] + self.shortest_lanes(nxt, l1)
                length = sum(self.lanes[x].length for x in path)
                if best is None or length < best[0]:
                    best = (length, path)
            lanes = best[1]
        return self.build_route(lanes, s0, s1, name)

    def build_route(self, lanes: list[str], s_start: float, s_goal: float, name: str = "route",
                    meta: dict | None = None) -> Route:
        """A Route along consecutive ``lanes`` from arc length ``s_start`` on the first lane to
        ``s_goal`` on the last, with commands and junction flags."""
        parts, turns_raw, acc = [], [], 0.0
        for k, lid in enumerate(lanes):
            lane = self.lanes[lid]
            a = s_start if k == 0 else 0.0
            b = s_goal if k == len(lanes) - 1 else lane.length
            if b <= a + 1e-6:
                raise ValueError(f"route {name!r}: empty piece on lane {lid} ({a:.1f}..{b:.1f} m)")
            piece = _slice(lane.points, a, b)
            parts.append(piece)
            acc += float(_cum(piece)[-1])
            if k + 1 < len(lanes):
                if (lid, lanes[k + 1]) not in self.connectors:
                    raise ValueError(f"route {name!r}: lane {lid} does not lead to lane {lanes[k + 1]}")
                c = self.connectors[(lid, lanes[k + 1])]
                parts.append(c.points)
                turns_raw.append((c.junction, c.command, acc, acc + c.length))
                acc += c.length
        raw = np.vstack(parts)
        keep = np.concatenate([[True], np.linalg.norm(np.diff(raw, axis=0), axis=1) > 1e-6])
        raw = raw[keep]
        pts = resample(raw, STEP)
        s = _cum(pts)
        k = s[-1] / acc  # resampling shortens the polyline a hair: keep turn positions proportional
        turns = tuple((j, c, e * k, x * k) for j, c, e, x in turns_raw)
        heading = np.unwrap(_heading(pts))
        curv = np.gradient(heading, s) if len(s) > 2 else np.zeros(len(s))
        curv = np.convolve(curv, np.ones(5) / 5, mode="same")
        commands, in_j = turn_commands(s, turns, self.command_distance)
        return Route(name=name, points=pts, heading=_wrap(heading), s=s, curvature=curv, commands=commands,
                     in_junction=in_j, lanes=tuple(lanes), turns=turns, meta=dict(meta or {}))

    # ------------------------------------------------------------------------------------------

    def random_route(self, rng: np.random.Generator, min_length: float, name: str = "random",
                     counts: dict | None = None) -> Route:
        """A random route of at least ``min_length`` m from a random lane point; at each junction the
        exit is drawn favouring the commands driven least so far (``counts``: command -> metres under
        that command, updated in place; weight 1 / (1 + metres / 10)^2), so turns stay balanced across a dataset."""
        lane_ids = sorted(self.lanes)
        first = lane_ids[int(rng.integers(len(lane_ids)))]
        s0 = float(rng.uniform(0.0, max(self.lanes[first].length - 1.0, 0.5)))
        lanes, total = [first], self.lanes[first].length - s0
        while total < min_length + 10.0:
            outs = sorted(self.out[lanes[-1]])
            cmds = [self.connectors[(lanes[-1], o)].command for o in outs]
            if counts is not None:
                w = np.array([1.0 / (1.0 + counts.get(c, 0.0) / 10.0) for c in cmds]) ** 2
            else:
                w = np.ones(len(outs))
            nxt = outs[int(rng.choice(len(outs), p=w / w.sum()))]
            if counts is not None:  # metres under each command: right turns are short, so count length
                con = self.connectors[(lanes[-1], nxt)]
                counts[con.command] = counts.get(con.command, 0.0) + con.length + self.command_distance
            total += self.connectors[(lanes[-1], nxt)].length + self.lanes[nxt].length
            lanes.append(nxt)
        last = self.lanes[lanes[-1]]
        s_goal = last.length - (total - min_length - 10.0)
        s_goal = float(np.clip(s_goal, 0.5, last.length))
        if len(lanes) == 1:
            s_goal = max(s_goal, s0 + 1.0)
        return self.build_route(lanes, s0, s_goal, name=name)


@functools.lru_cache(maxsize=8)  # a Town hashes by identity (eq=False)
def road_graph(town: Town, command_distance: float = COMMAND_DISTANCE) -> RoadGraph:
    """The (cached) RoadGraph of a town."""
    return RoadGraph(town, command_distance)


def single_turn_routes(town: Town, before: float = 30.0, after: float = 25.0,
                       command_distance: float = COMMAND_DISTANCE) -> list[Route]:
    """The closed-loop suite's routes: one per possible manoeuvre (left / right / straight from each
    incoming lane) at every junction, so together they cover every junction and every turn.

    Each route starts ``before`` metres before the junction on the incoming lane (less if the lane is
    shorter: it never starts inside the previous junction) and ends ``after`` metres past it on the
    outgoing lane, so exactly one turn decision is needed. Sorted by (junction, incoming, outgoing
    lane); the same town file always gives the same list. Names are
    ``<town>/<junction>/<in road>><out road>/<command>``.
    """
    g = road_graph(town, command_distance)
    routes = []
    for c in sorted(g.connectors.values(), key=lambda c: (c.junction, c.src, c.dst)):  # every manoeuvre
        li, lo = g.lanes[c.src], g.lanes[c.dst]
        s0 = max(li.length - before, min(2.0, li.length / 2))
        s1 = min(after, lo.length - 2.0)
        name = f"{town.name}/{c.junction}/{li.road}>{lo.road}/{COMMAND_NAMES[c.command]}"
        routes.append(g.build_route([li.id, lo.id], s0, s1, name=name,
                                    meta={"junction": c.junction, "command": c.command,
                                          "from_road": li.road, "to_road": lo.road}))
    return routes
