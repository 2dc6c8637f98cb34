"""The per-step episode information and the rule that ends an episode, shared by every backend.

``cicfw.sim.env.DrivingEnv`` and ``cicfw.carla_client.backend.CarlaEnv`` both return
``step_info(...)`` from ``info()``; each measures the lane fractions its own way (the embedded town
map, CARLA's waypoints) and CARLA adds its sensor events and ``frame``.
"""
from __future__ import annotations

import math

from cicfw.sim.roadgraph import Route


def step_info(route: Route, x: float, y: float, i: int, t: float, success_radius: float, timeout: float,
              max_deviation: float, lanes: tuple[bool, float, float]) -> dict:
    """The info of a car whose rear axle is at (x, y), at point ``i`` of ``route`` (``Expert.locate``),
    ``t`` s into the episode; ``lanes`` = (in_junction, opposite-lane fraction, off-road fraction).

    ``reason``, checked in this order: "success" within ``success_radius`` m of the route's goal,
    "timeout" at ``t >= timeout`` (less 1e-9 for the clock's float steps), "lost" beyond
    ``max_deviation`` m from route point ``i``, else None (the episode goes on)."""
    gx, gy = route.goal
    dist = math.hypot(gx - x, gy - y)
    px, py = route.points[i]
    dev = math.hypot(px - x, py - y)
    in_j, opp, off = lanes
    reason = None
    if dist <= success_radius:
        reason = "success"
    elif t >= timeout - 1e-9:
        reason = "timeout"
    elif dev > max_deviation:
        reason = "lost"
    return {"distance_to_goal": dist, "route_deviation": dev,
            "progress": float(route.s[i] / max(route.length, 1e-9)),
            "opposite_lane": opp, "off_road": off, "in_junction": in_j,
            "success": reason == "success", "reason": reason, "t": t}
