"""Vehicle model, expert, CIL noise, the driving env and the world lookups (no rendering here)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from cicfw.registry import SIM_BACKENDS
from cicfw.sim.env import DrivingEnv, run_expert
from cicfw.sim.expert import ExpertParams, Noiser, speed_profile
from cicfw.sim.roadgraph import LEFT, RIGHT, road_graph, single_turn_routes
from cicfw.sim.town import load_town
from cicfw.sim.townmap import town_map
from cicfw.sim.vehicle import SpeedController, Vehicle, VehicleParams, VehicleState


def test_vehicle_straight_and_turning_geometry():
    v = Vehicle(VehicleState(0.0, 0.0, 0.0, speed=10.0), VehicleParams(drag=0.0, rolling=0.0))
    for _ in range(10):
        v.step(0.0, 0.0, 0.0)  # coasting, no resistance
    assert v.s.x == pytest.approx(10.0, abs=1e-6) and v.s.y == pytest.approx(0.0, abs=1e-9)
    # positive steer turns right (yaw decreases); the circle has radius wheelbase / tan(wheel angle)
    v = Vehicle(VehicleState(0.0, 0.0, 0.0, speed=5.0), VehicleParams(drag=0.0, rolling=0.0))
    xs, ys = [], []
    for _ in range(200):
        v.step(0.5, 0.0, 0.0)
        xs.append(v.s.x)
        ys.append(v.s.y)
    radius = v.p.wheelbase / math.tan(math.radians(0.5 * v.p.max_wheel_angle_deg))
    centre = np.array([0.0, -radius])  # to the right of a car heading +x
    d = np.hypot(np.array(xs) - centre[0], np.array(ys) - centre[1])
    assert np.allclose(d, radius, atol=1e-6)
    assert min(ys) < -radius  # went round to the right
    # the steering that drives a path of curvature -1/radius (1/m, positive = left)
    assert -math.atan(-1 / radius * v.p.wheelbase) / math.radians(v.p.max_wheel_angle_deg) == pytest.approx(0.5)


def test_throttle_brake_and_speed_controller():
    v = Vehicle(VehicleState(0.0, 0.0, 0.0))
    for _ in range(20):
        v.step(0.0, 1.0, 0.0)
    assert 5.0 < v.s.speed < 8.0  # ~4 m/s^2 from standstill, less as speed grows
    for _ in range(20):
        v.step(0.0, 0.0, 1.0)
    assert v.s.speed == 0.0  # full brake stops and never reverses
    ctl = SpeedController()
    v = Vehicle(VehicleState(0.0, 0.0, 0.0))
    for _ in range(150):
        v.step(0.0, *ctl(v.s.speed, 25 / 3.6))
    assert v.s.speed_kmh == pytest.approx(25.0, abs=1.0)
    for _ in range(60):
        v.step(0.0, *ctl(v.s.speed, 12 / 3.6))
    assert v.s.speed_kmh == pytest.approx(12.0, abs=1.0)


def test_speed_profile_slows_before_turns():
    town = load_town("town_a")
    r = next(r for r in single_turn_routes(town) if r.meta["command"] == RIGHT)
    p = ExpertParams()
    v = speed_profile(r, p) * 3.6
    entry = r.turns[0][2]
    assert v[0] == pytest.approx(p.cruise_kmh, abs=0.5)
    assert 10.0 <= v[r.in_junction].min() <= 16.0
    assert v[np.searchsorted(r.s, entry - 3.0)] < 18.0  # already slow when entering the junction


def test_noiser_follows_cil_and_never_touches_the_label():
    rng = np.random.default_rng(0)
    nz = Noiser(rng)
    assert 8 <= nz.intensity <= 12
    applied, flags = [], []
    for _ in range(6000):  # 10 minutes at 15 km/h, constant expert steering 0.1
        a, f = nz.step(0.1, 15.0)
        applied.append(a)
        flags.append(f)
    applied, flags = np.array(applied), np.array(flags)
    scale = 25 / (2.3 * 15 + 5)
    assert np.all(np.abs(applied - 0.1) <= 0.55 * scale + 1e-6)  # capped at 0.55 before scaling
    assert np.abs(applied - 0.1).max() == pytest.approx(0.55 * scale, abs=1e-6)
    assert np.all(applied[~flags] == 0.1)  # no noise without the flag
    assert np.any(applied[flags] != 0.1)
    # spikes: ~15/61 per second start -> a few dozen in 10 minutes; each lasts >= 2.5 s
    starts = np.flatnonzero(np.diff(flags.astype(int)) == 1)
    assert 25 <= len(starts) <= 110
    assert 0.3 < flags.mean() < 0.8
    ends = np.flatnonzero(np.diff(flags.astype(int)) == -1)
    lengths = (ends[: len(starts)] - starts[: len(ends)]) * 0.1
    assert lengths.min() >= 2.5
    # ramp rate: 0.03 * intensity per second (before the cap)
    k = starts[0] + 1
    assert abs(applied[k + 1] - applied[k]) == pytest.approx(0.03 * nz.intensity * 0.1 * scale, rel=1e-4)
    off = Noiser(np.random.default_rng(0), enabled=False)
    assert off.step(0.3, 20.0) == (0.3, False)


def test_expert_completes_single_turn_routes_clean_and_noisy():
    for name in ("town_a", "town_b"):
        town = load_town(name)
        routes = single_turn_routes(town)[::7]
        for k, r in enumerate(routes):
            for noise in (None, np.random.default_rng(k)):
                info = run_expert(DrivingEnv(town, r, renderer=False), noise)
                assert info["success"], (r.name, info)
                assert info["t"] < r.timeout()


def test_env_reports_lanes_and_ends_episodes():
    town = load_town("town_a")
    r = next(r for r in single_turn_routes(town) if r.meta["command"] == LEFT)
    env = DrivingEnv(town, r, renderer=False)
    obs = env.reset()
    assert obs["images"] == {} and obs["command"] == 2 and obs["speed_kmh"] == 0.0
    assert obs["pose"] == pytest.approx(r.start_pose)
    seen = set()
    done = False
    while not done:
        steer, v = env.expert_action()
        obs, done, info = env.step(steer, target_speed_kmh=v)
        seen.add(obs["command"])
        assert info["opposite_lane"] == 0.0 and info["off_road"] == 0.0
    assert seen == {2, 3} and info["reason"] == "success" and info["distance_to_goal"] <= 2.0
    with pytest.raises(RuntimeError, match="reset"):
        env.step(0.0, target_speed_kmh=10.0)
    # steering hard left off the route: the car ends up on the opposite lane, then lost
    env.reset()
    opp = []
    done = False
    while not done:
        obs, done, info = env.step(-0.3, target_speed_kmh=20.0)
        opp.append(info["opposite_lane"])
    assert max(opp) == 1.0 and info["reason"] in ("lost", "timeout")


def test_town_map_sides():
    town = load_town("town_a")
    m = town_map(town)
    road = town.road("s1-s2")  # runs east along y = 0
    x = float(road.centreline[len(road.centreline) // 2, 0])
    hw = town.lane_width
    assert m.query(x, -hw / 2, 0.0)[1:3] == (0.0, 0.0)  # eastbound in the right (south) lane
    assert m.query(x, +hw / 2, 0.0)[1] == 1.0  # eastbound in the north lane: opposite
    assert m.query(x, +hw / 2, math.pi)[1] == 0.0  # westbound there: own lane
    assert m.query(x, -hw - 1.5, 0.0)[2] > 0.9  # on the sidewalk
    assert m.query(165.0, 0.0, 0.0)[0]  # junction s2


def test_random_routes_are_long_and_turn_balanced():
    g = road_graph(load_town("town_a"))
    counts: dict = {}
    r = g.random_route(np.random.default_rng(3), 2000.0, counts=counts)
    assert r.length >= 2000.0
    cmds = [t[1] for t in r.turns]
    assert {3, 4, 5} <= set(cmds)
    for c in (3, 4, 5):
        assert cmds.count(c) >= len(cmds) // 6


def test_backends_registered_and_carla_error_is_clear():
    assert {"embedded", "carla"} <= set(SIM_BACKENDS.names())
    b = SIM_BACKENDS.get("embedded")()
    assert len(b.single_turn_routes("town_b")) == len(single_turn_routes(load_town("town_b")))
    env = b.make_env("town_b", b.single_turn_routes("town_b")[0], "ClearNoon", renderer=False)
    assert env.reset()["command"] in (2, 3, 4, 5)
    try:
        import carla  # noqa: F401
    except ImportError:
        with pytest.raises(ImportError, match=r"pip install cicfw\[carla\].*server"):
            SIM_BACKENDS.get("carla")()


def test_sim_and_town_configs_are_valid_hydra_options():
    from hydra import compose, initialize_config_module

    from cicfw.sim.town import load_town, town_names

    with initialize_config_module("cicfw.conf", version_base="1.3"):
        for name in ("embedded", "carla"):
            cfg = compose("collect", overrides=[f"sim={name}"])
            assert cfg.sim.name in SIM_BACKENDS
        b = SIM_BACKENDS.get("embedded")(**{k: v for k, v in compose("collect", overrides=["sim=embedded"]).sim.items()
                                            if k != "name"})
        assert b.command_distance == 12.0
        for town in town_names():
            assert compose(f"town/{town}").town.name == load_town(town).name  # no app config takes +town
