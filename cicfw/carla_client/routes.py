"""Routes on a CARLA map (``carla.Map``), planned with the Map API only (the wheel has no ``agents``).

Everything here works offline: ``carla.Map(name, xodr_text)`` builds the same map a server serves, so
the suite's routes are computed and tested without a server (tests/test_carla_routes.py).

Coordinates: CARLA's frame is left-handed (x forward, y right, yaw clockwise seen from above); cicfw's
is right-handed (yaw counter-clockwise). A CARLA point (x, y) is cicfw's (x, -y), a CARLA yaw (deg) is
cicfw's ``-radians(yaw)``.
"""
from __future__ import annotations

import math
from typing import Any, Iterable

import numpy as np

from cicfw.sim.roadgraph import COMMAND_DISTANCE, COMMAND_NAMES, Route, turn_code, turn_commands

STEP = 0.5  # metres between route points


def heading_change_deg(yaw_in_carla: float, yaw_out_carla: float) -> float:
    """The heading change from CARLA yaw ``yaw_in`` to ``yaw_out`` (degrees), in cicfw's sense:
    positive = left (counter-clockwise)."""
    return -((yaw_out_carla - yaw_in_carla + 180.0) % 360.0 - 180.0)


def _walk(wp: Any, length: float, step: float, forward: bool) -> list:
    """The waypoints ahead of (``forward``) or behind ``wp`` along its lane, nearest first, ``wp``
    excluded, up to ``length`` m, stopping before any junction."""
    out: list = []
    cur, done = wp, 0.0
    while done + step <= length + 1e-6:
        cand = [w for w in (cur.next(step) if forward else cur.previous(step)) if not w.is_junction]
        if not cand:
            break
        cur = min(cand, key=lambda w: (w.road_id != cur.road_id, w.lane_id != cur.lane_id))
        out.append(cur)
        done += step
    return out


def build_route(wps: list, turns: Iterable[tuple], name: str, command_distance: float = COMMAND_DISTANCE,
                step: float = STEP, meta: dict | None = None) -> Route:
    """A cicfw ``Route`` from CARLA waypoints in driving order.

    ``turns``: ``(junction id, code, first index, last index)`` of each junction lane in ``wps``.
    Points closer than ``step / 4`` to the previous kept point are dropped (the join of two walks);
    heading is the waypoints' own (the lane's direction), curvature its change per metre.
    """
    keep, kept_idx = [], {}
    last = None
    for k, w in enumerate(wps):
        loc = w.transform.location
        if last is not None and math.hypot(loc.x - last.x, loc.y - last.y) < step / 4:
            kept_idx[k] = len(keep) - 1
            continue
        kept_idx[k] = len(keep)
        keep.append(w)
        last = loc
    pts = np.array([[w.transform.location.x, -w.transform.location.y] for w in keep], float)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    heading = np.unwrap(np.array([-math.radians(w.transform.rotation.yaw) for w in keep]))
    curvature = np.gradient(heading, s) if len(s) > 1 else np.zeros(len(s))
    heading = (heading + np.pi) % (2 * np.pi) - np.pi
    out_turns = [(f"j{jid}", int(code), float(s[kept_idx[i0]]), float(s[kept_idx[i1]])) for jid, code, i0, i1 in turns]
    cmds, in_j = turn_commands(s, out_turns, command_distance)
    start = keep[0].transform
    meta = dict(meta or {})
    meta["spawn"] = (float(start.location.x), float(start.location.y), float(start.location.z),
                     float(start.rotation.yaw))
    meta["start_lane"] = (int(keep[0].road_id), int(keep[0].section_id), int(keep[0].lane_id))
    return Route(name=name, points=pts, heading=heading, s=s, curvature=curvature, commands=cmds,
                 in_junction=in_j, lanes=(), turns=tuple(out_turns), meta=meta)


def _lane_turn(wp: Any, step: float) -> tuple[list, int, float]:
    """The junction lane starting at ``wp``: its waypoints, CIL code and heading change (deg)."""
    lane = [wp] + list(wp.next_until_lane_end(step))
    change = heading_change_deg(lane[0].transform.rotation.yaw, lane[-1].transform.rotation.yaw)
    return lane, turn_code(change), change


def single_turn_routes(cmap: Any, town: str, before: float = 30.0, after: float = 25.0,
                       command_distance: float = COMMAND_DISTANCE, step: float = STEP) -> list[Route]:
    """The suite's routes on ``cmap``: one per lane through a junction, sorted by name
    ``<town>/j<junction>/<road>:<lane>/<left|right|straight>`` (stable for a map)."""
    routes = []
    for wp_a, _ in cmap.get_topology():
        if not wp_a.is_junction:
            continue  # keep the lanes inside junctions: one per manoeuvre
        lane, code, change = _lane_turn(wp_a, step)
        back = _walk(wp_a, before, step, forward=False)[::-1]
        exit_ = [w for w in lane[-1].next(step) if not w.is_junction]
        if not back or not exit_:
            continue  # a junction lane straight into another junction: no single-turn route
        wps = back + lane + [exit_[0]] + _walk(exit_[0], after, step, forward=True)
        jid = wp_a.get_junction().id
        name = f"{town}/j{jid}/{wp_a.road_id}:{wp_a.lane_id}/{COMMAND_NAMES[code]}"
        routes.append(build_route(wps, [(jid, code, len(back), len(back) + len(lane) - 1)], name,
                                  command_distance, step,
                                  meta={"command": code, "junction": int(jid), "heading_change_deg": change}))
    return sorted(routes, key=lambda r: r.name)


def random_route(cmap: Any, rng: np.random.Generator, min_length: float, name: str = "random",
                 counts: dict | None = None, command_distance: float = COMMAND_DISTANCE,
                 step: float = STEP) -> Route:
    """A route of at least ``min_length`` m from a random point of a driving lane outside junctions.

    At each junction the lane is drawn favouring the commands driven least so far (``counts``: command
    -> metres under it, updated in place; weight 1 / (1 + metres / 10)^2), as the embedded planner."""
    starts = [w for w in cmap.generate_waypoints(2.0) if not w.is_junction]
    if not starts:
        raise ValueError(f"map {cmap.name!r} has no driving lane outside junctions")
    wps = [starts[int(rng.integers(len(starts)))]]
    turns = []
    length = 0.0
    while length < min_length + 10.0:
        nxt = wps[-1].next(step)
        if not nxt:
            raise ValueError(f"map {cmap.name!r}: the lane at road {wps[-1].road_id} lane {wps[-1].lane_id} "
                             f"ends with no successor ({length:.0f} m into a route of {min_length:.0f} m)")
        if any(w.is_junction for w in nxt):
            options = sorted((_lane_turn(w, step) for w in nxt if w.is_junction),
                             key=lambda o: (o[0][0].road_id, o[0][0].lane_id))
            cmds = [o[1] for o in options]
            w8 = np.array([1.0 / (1.0 + (counts or {}).get(c, 0.0) / 10.0) for c in cmds]) ** 2
            lane, code, _ = options[int(rng.choice(len(options), p=w8 / w8.sum()))]
            lane_len = step * (len(lane) - 1)
            if counts is not None:
                counts[code] = counts.get(code, 0.0) + lane_len + command_distance
            turns.append((lane[0].get_junction().id, code, len(wps), len(wps) + len(lane) - 1))
            wps += lane
            length += lane_len + step
        else:
            wps.append(min(nxt, key=lambda w: (w.road_id != wps[-1].road_id, w.lane_id != wps[-1].lane_id)))
            length += step
    return build_route(wps, turns, name, command_distance, step, meta={"town": cmap.name})
