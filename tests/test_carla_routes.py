"""The CARLA backend's routes on CARLA's real Town01 and Town02, offline: the real ``carla`` client
builds the maps from the OpenDRIVE files in ../shared/carla-maps (no server).

Labels are checked against a classification computed here from the route's own points and the map's
junction membership (not from the waypoint yaws the planner uses)."""
from __future__ import annotations

import collections
import math

import numpy as np
import pytest

carla = pytest.importorskip("carla", reason="the CARLA client is not installed: pip install -e '.[carla]'")

from cicfw.carla_client.routes import random_route, single_turn_routes  # noqa: E402
from carla_standin import maps_dir  # noqa: E402
from cicfw.sim.expert import Expert  # noqa: E402

MAPS = maps_dir()
pytestmark = pytest.mark.skipif(MAPS is None, reason="CARLA's Town01/Town02 OpenDRIVE files are not in "
                                                     "../shared/carla-maps (or $CICFW_CARLA_MAPS)")
# junctions, left, right, straight (CARLA's own maps, counted on the OpenDRIVE files)
EXPECTED = {"Town01": (12, 24, 24, 24), "Town02": (8, 16, 16, 16)}


@pytest.fixture(scope="module", params=["Town01", "Town02"])
def town(request):
    cmap = carla.Map(request.param, (MAPS / f"{request.param}.xodr").read_text())
    return request.param, cmap, single_turn_routes(cmap, request.param)


def _junctions_along(cmap, route) -> list:
    """The junction id of every route point (None outside junctions), from the map itself."""
    out = []
    for x, y in route.points:
        wp = cmap.get_waypoint(carla.Location(x=float(x), y=float(-y), z=0.0), project_to_road=False)
        out.append(wp.get_junction().id if wp is not None and wp.is_junction else None)
    return out


def _independent_turn(route, junction_ids) -> int:
    """Left (3) / right (4) / straight (5) from the points' own heading 5 m before the first and 5 m after
    the last point inside the junction (cicfw frame: counter-clockwise positive)."""
    inside = [i for i, j in enumerate(junction_ids) if j is not None]
    s_in, s_out = route.s[inside[0]], route.s[inside[-1]]

    def direction(s0, s1):
        i0, i1 = np.searchsorted(route.s, [s0, s1])
        d = route.points[min(i1, len(route.s) - 1)] - route.points[i0]
        return math.atan2(d[1], d[0])

    change = math.degrees((direction(s_out, s_out + 5) - direction(s_in - 5, s_in) + math.pi) % (2 * math.pi) - math.pi)
    return 5 if abs(change) < 45 else (3 if change > 0 else 4)


def test_counts_and_labels_against_the_geometry(town):
    name, cmap, routes = town
    junctions, left, right, straight = EXPECTED[name]
    labels = collections.Counter(r.meta["command"] for r in routes)
    assert (len(routes), labels[3], labels[4], labels[5]) == (left + right + straight, left, right, straight)
    assert len({r.meta["junction"] for r in routes}) == junctions
    wrong = []
    for r in routes:
        ids = _junctions_along(cmap, r)
        if _independent_turn(r, ids) != r.meta["command"]:
            wrong.append(r.name)
    assert not wrong, f"labels that disagree with the geometry: {wrong}"
    assert len({r.name for r in routes}) == len(routes) and [r.name for r in routes] == sorted(r.name for r in routes)


def test_every_route_has_finite_curvature_and_speed_targets(town):
    _, _, routes = town
    for r in routes:
        assert np.all(np.diff(r.s) > 0.1), f"{r.name}: a step of {np.diff(r.s).min():.3f} m"
        assert np.all(np.isfinite(r.curvature)), r.name
        assert np.abs(r.curvature).max() < 0.5, f"{r.name}: curvature {np.abs(r.curvature).max():.2f} 1/m"
        profile = Expert(r).profile
        assert np.all(np.isfinite(profile)) and profile.min() > 0, r.name
        # the turn command covers the junction, follow-lane before it
        assert r.commands[0] == 2 and set(r.commands[r.in_junction]) == {r.meta["command"]}


def test_every_route_passes_exactly_one_junction_and_starts_outside_junctions(town):
    _, cmap, routes = town
    for r in routes:
        ids = _junctions_along(cmap, r)
        met = {j for j in ids if j is not None}
        assert met == {r.meta["junction"]}, f"{r.name} passes junctions {met}"
        assert ids[0] is None and ids[-1] is None, f"{r.name} starts or ends inside a junction"
        inside = [i for i, j in enumerate(ids) if j is not None]
        assert r.s[inside[0]] > 20.0 and r.length - r.s[inside[-1]] > 20.0, r.name  # room before and after


def test_spawn_poses_lie_on_their_lanes(town):
    _, cmap, routes = town
    for r in routes:
        x, y, z, yaw = r.meta["spawn"]
        wp = cmap.get_waypoint(carla.Location(x=x, y=y, z=z), project_to_road=False)
        assert wp is not None and wp.lane_type == carla.LaneType.Driving and not wp.is_junction, r.name
        assert (wp.road_id, wp.section_id, wp.lane_id) == r.meta["start_lane"], r.name
        assert abs((wp.transform.rotation.yaw - yaw + 180.0) % 360.0 - 180.0) < 5.0, r.name
        # the spawn is the route's first point in cicfw's frame (y mirrored, heading -yaw)
        assert np.allclose(r.points[0], (x, -y), atol=1e-6)
        assert abs((math.degrees(-r.heading[0]) - yaw + 180.0) % 360.0 - 180.0) < 1e-3


def test_random_collection_routes_are_finite_and_balanced(town):
    name, cmap, _ = town
    rng, counts = np.random.default_rng(0), {}
    routes = [random_route(cmap, rng, 150.0, f"{name}-{k}", counts) for k in range(12)]
    for r in routes:
        assert r.length >= 150.0 and np.all(np.isfinite(r.curvature)) and np.all(np.isfinite(Expert(r).profile))
        assert np.all(np.diff(r.s) > 0.1)
        ids = _junctions_along(cmap, r)
        assert ids[0] is None  # never starts inside a junction
        # a junction id on the map for every turn the route lists, in order
        passed = [j for k, j in enumerate(ids) if j is not None and (k == 0 or ids[k - 1] != j)]
        assert [int(t[0][1:]) for t in r.turns] == passed
    assert sum(len(r.turns) for r in routes) >= 12
    metres = [counts.get(c, 0.0) for c in (3, 4, 5)]
    assert min(metres) > 0.5 * max(metres), metres
