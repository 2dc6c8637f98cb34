"""The per-step episode info both backends return (``cicfw.sim.episode.step_info``): its values, worked
out by hand on a straight 100 m route, each reason an episode ends for, and the order of the checks."""
from __future__ import annotations

import math

import numpy as np
import pytest

from cicfw.sim.episode import step_info
from cicfw.sim.roadgraph import Route

N = 101  # one point a metre along +x, from (0, 0) to the goal (100, 0)
ROUTE = Route(name="straight", points=np.stack([np.arange(N, dtype=float), np.zeros(N)], axis=1),
              heading=np.zeros(N), s=np.arange(N, dtype=float), curvature=np.zeros(N),
              commands=np.full(N, 2, dtype=np.int8), in_junction=np.zeros(N, dtype=bool), lanes=(), turns=())
RULES = dict(success_radius=2.0, timeout=30.0, max_deviation=10.0)
LANES = (False, 0.0, 0.0)


def info(x: float, y: float, i: int, t: float, lanes: tuple = LANES, **rules) -> dict:
    return step_info(ROUTE, x, y, i, t, lanes=lanes, **{**RULES, **rules})


def test_the_values_and_their_keys_in_order():
    got = info(97.0, 4.0, 97, 12.5, lanes=(True, 0.25, 0.5))
    assert list(got) == ["distance_to_goal", "route_deviation", "progress", "opposite_lane", "off_road",
                         "in_junction", "success", "reason", "t"]
    assert got == {"distance_to_goal": 5.0,  # (3, 4) short of the goal
                   "route_deviation": 4.0,  # 4 m beside point 97
                   "progress": 0.97, "opposite_lane": 0.25, "off_road": 0.5, "in_junction": True,
                   "success": False, "reason": None, "t": 12.5}
    assert info(50.0, 3.0, 50, 1.0)["distance_to_goal"] == math.sqrt(50 ** 2 + 3 ** 2)


@pytest.mark.parametrize("x, y, i, t, reason", [
    (100.0, 2.0, 100, 5.0, "success"),  # exactly the success radius away counts
    (100.0, 2.5, 100, 5.0, None),
    (50.0, 0.0, 50, 30.0 - 1e-10, "timeout"),  # the clock's float steps: within 1e-9 of the timeout
    (50.0, 0.0, 50, 29.9, None),
    (40.0, 10.5, 40, 5.0, "lost"),  # 10.5 m off point 40
    (40.0, 10.0, 40, 5.0, None),  # exactly max_deviation is still on the route
])
def test_each_reason_and_its_threshold(x, y, i, t, reason):
    got = info(x, y, i, t)
    assert got["reason"] == reason and got["success"] == (reason == "success")


@pytest.mark.parametrize("x, y, i, t, reason", [
    (100.0, 0.0, 100, 31.0, "success"),  # at the goal and past the timeout
    (100.0, 0.0, 0, 5.0, "success"),  # at the goal and 100 m from point 0
    (40.0, 50.0, 40, 31.0, "timeout"),  # past the timeout and lost
    (100.0, 0.0, 0, 31.0, "success"),  # all three
])
def test_success_is_checked_before_the_timeout_and_the_timeout_before_lost(x, y, i, t, reason):
    got = info(x, y, i, t)
    assert got["reason"] == reason and got["success"] == (reason == "success")


def test_the_endless_rules_of_collection_never_end_an_episode():
    got = info(100.0, 0.0, 0, 1e6, success_radius=-1.0, timeout=1e9, max_deviation=1e9)
    assert got["reason"] is None and got["distance_to_goal"] == 0.0 and got["route_deviation"] == 100.0
