"""CARLA episodes driven offline through a recording stand-in server (``tests/carla_standin.py``:
autospecs of the real ``carla`` classes, the real Town01/Town02 maps, calls bound to the wheel's stubs).

What a whole evaluation run does to the server: one episode at a time, each with its own town, weather
and car; one tick per step; the image of the ticked frame; no non-finite control; the world's settings
restored and no actor left after success, an exception, a missing frame and Ctrl-C."""
from __future__ import annotations

import logging
import math
import time

import numpy as np
import pytest

carla = pytest.importorskip("carla", reason="the CARLA client is not installed: pip install -e '.[carla]'")

from cicfw.benchmark.builtin_policies import ConstantPolicy, ExpertPolicy  # noqa: E402
from cicfw.benchmark.runner import RunnerConfig, run, server_specs  # noqa: E402
from cicfw.benchmark.suite import build_suite  # noqa: E402
from cicfw.carla_client.backend import (CarlaBackend, CarlaBusy, CarlaSensorTimeout,  # noqa: E402
                                        steer_for_car)
from carla_standin import StandIn, maps_dir  # noqa: E402
from cicfw.sim.vehicle import VehicleParams  # noqa: E402

MAPS = maps_dir()
pytestmark = [pytest.mark.slow,  # drives whole episodes (pytest -m "not slow" skips it)
              pytest.mark.skipif(MAPS is None, reason="CARLA's Town01/Town02 OpenDRIVE files are not in "
                                                      "../shared/carla-maps (or $CICFW_CARLA_MAPS)")]
SETTLE = 2
CAMS = ("centre", "left", "right")


def make(**standin) -> tuple[StandIn, CarlaBackend]:
    si = StandIn(MAPS, image_size_override=standin.pop("image_size_override", (200, 150)), **standin)
    return si, CarlaBackend(client=si.client, settle_ticks=SETTLE, sensor_timeout_s=0.3)


def episodes_in_log(si: StandIn) -> list[dict]:
    return si.episodes()  # raises if two cars were alive at once or one was never destroyed


def assert_clean(si: StandIn) -> None:
    assert si.leftovers() == []


class CameraExpert(ExpertPolicy):
    """The expert, with the three cameras on; records the frame each image encodes."""

    cameras = CAMS

    def __init__(self, fail_at: int | None = None) -> None:
        super().__init__()
        self.seen: list[dict] = []
        self.fail_at = fail_at

    def act(self, obs):
        if self.fail_at is not None and len(self.seen) == self.fail_at:
            raise RuntimeError("the policy broke")
        self.seen.append({c: (StandIn.decode_frame(obs.images[c][0]), int(obs.images[c][0][44, 100, 0]))
                          for c in CAMS})
        return super().act(obs)


def test_a_run_drives_episodes_one_at_a_time_each_with_its_town_weather_and_one_tick_per_step():
    si, be = make()
    eps = build_suite(be, ["town_a", "town_b"], ["ClearNoon", "WetCloudySunset"], training_towns=["town_a"],
                      pairs=[1])
    res = run(eps, ExpertPolicy(), be, RunnerConfig(workers=1, progress_bar=False))
    assert [r["reason"] for r in res.rows] == ["success"] * 4
    logged = episodes_in_log(si)
    assert len(logged) == 4
    for ep, row, got in zip(eps, res.rows, logged):
        ticks = got["ticks"]
        assert len(ticks) == SETTLE + 1 + row["steps"]  # the reset's ticks, then exactly one per step
        assert {t[2] for t in ticks} == {ep.weather}  # every tick under this episode's own weather
        assert {t[5] for t in ticks} == {be.carla_town(ep.town)}  # in this episode's town
        assert {(t[3], t[4]) for t in ticks} == {(True, 0.1)}  # synchronous at 10 Hz
        assert np.all(np.diff([t[1] for t in ticks]) == 1)
        assert row["offroad_fraction"] == 0.0 and row["opposite_lane_fraction"] == 0.0
    assert_clean(si)


def test_every_camera_image_is_the_ticked_frame_even_with_a_backlog_and_late_delivery():
    si, be = make()
    si.backlog = True  # each camera also sends the previous frame before and an older one after
    si.delay_s = 0.02  # from another thread, after tick() returned
    eps = build_suite(be, ["town_a"], ["ClearNoon"], pairs=[0])
    pol = CameraExpert()
    res = run(eps, pol, be, RunnerConfig(workers=1, progress_bar=False))
    assert res.rows[0]["success"]
    ticks = [t[1] for t in episodes_in_log(si)[0]["ticks"]]
    observed = ticks[SETTLE:SETTLE + res.rows[0]["steps"]]  # reset's last tick, then every step's but the last
    for k, cam in enumerate(CAMS):
        assert [s[cam][0] for s in pol.seen] == observed, f"camera {cam} lags its tick"
        assert {s[cam][1] for s in pol.seen} == {k}  # each camera's own image (not another's)
    assert_clean(si)


def test_full_size_images_are_cropped_and_resized_as_cil():
    si = StandIn(MAPS)  # 800 x 600, as requested by the blueprint
    be = CarlaBackend(client=si.client, settle_ticks=SETTLE)
    route = be.single_turn_routes("town_a")[0]
    with be.make_env("town_a", route, "ClearNoon", cameras=CAMS) as env:
        obs = env.reset()
        cams = [r for r in si.alive.values() if r["kind"] == "camera"]
        assert len(cams) == 3 and all(r["attrs"]["image_size_x"] == "800" and r["attrs"]["image_size_y"] == "600"
                                      and r["attrs"]["fov"] == "100.0" for r in cams)
        for c in CAMS:
            assert obs["images"][c].shape == (88, 200, 3) and obs["images"][c].dtype == np.uint8
            assert StandIn.decode_frame(obs["images"][c]) == env.frame == obs["frame"]
        obs, _, info = env.step(0.0, target_speed_kmh=10.0)
        assert StandIn.decode_frame(obs["images"]["left"]) == info["frame"] == si.frame
    assert_clean(si)


def test_a_missing_frame_is_one_clear_error_after_the_timeout_and_nothing_is_left():
    si, be = make()
    eps = build_suite(be, ["town_a"], ["ClearNoon"], pairs=[0])
    si.drop = {si.frame + SETTLE + 1 + 6}  # the 6th step's images never come
    t0 = time.monotonic()
    with pytest.raises(CarlaSensorTimeout) as err:
        run(eps, CameraExpert(), be, RunnerConfig(workers=1, progress_bar=False))
    assert "'centre'" in str(err.value) and "0.3 s" in str(err.value)  # the camera and the timeout
    assert time.monotonic() - t0 < 10.0
    assert_clean(si)


def test_an_exception_in_the_policy_leaves_nothing_behind():
    si, be = make()
    eps = build_suite(be, ["town_a"], ["ClearNoon"], pairs=[0, 1])
    with pytest.raises(RuntimeError, match="the policy broke"):
        run(eps, CameraExpert(fail_at=10), be, RunnerConfig(workers=1, progress_bar=False))
    assert len([e for e in si.log if e[0] == "spawn" and e[2].startswith("vehicle.")]) == 1
    assert_clean(si)


@pytest.mark.parametrize("when", ["reset", "step"])
def test_ctrl_c_leaves_nothing_behind(when):
    si, be = make()
    eps = build_suite(be, ["town_a"], ["ClearNoon"], pairs=[0])
    stop_at = si.frame + (1 if when == "reset" else SETTLE + 1 + 20)

    def interrupt(frame: int) -> None:
        if frame == stop_at:
            raise KeyboardInterrupt

    si.on_tick = interrupt
    with pytest.raises(KeyboardInterrupt):
        run(eps, ExpertPolicy(), be, RunnerConfig(workers=1, progress_bar=False))
    assert len(si.ticks()) == stop_at - 1 - 1000
    assert_clean(si)


def test_an_env_undoes_a_reset_that_fails_or_is_interrupted_without_anyone_closing_it():
    si, be = make()
    route = be.single_turn_routes("town_a")[0]
    env = be.make_env("town_a", route, "ClearNoon", cameras=CAMS)

    def interrupt(frame: int) -> None:
        raise KeyboardInterrupt

    si.on_tick = interrupt  # Ctrl-C during the settling ticks, after the car and sensors were spawned
    with pytest.raises(KeyboardInterrupt):
        env.reset()
    assert any(e[0] == "spawn" for e in si.log) and not env.live
    assert_clean(si)
    si.on_tick = None
    si.drop = set(range(si.frame, si.frame + 100))  # the cameras never deliver
    with pytest.raises(CarlaSensorTimeout):
        env.reset()
    assert_clean(si)


def test_one_episode_per_server():
    si, be = make()
    routes = be.single_turn_routes("town_a")
    first = be.make_env("town_a", routes[0], "ClearNoon", renderer=False)
    second = be.make_env("town_a", routes[1], "ClearSunset", renderer=False)
    with first:
        first.reset()
        with pytest.raises(CarlaBusy):
            second.reset()
        assert len([r for r in si.alive.values() if r["kind"] == "vehicle"]) == 1
    with second:
        second.reset()
        assert si.weather == "ClearSunset"
    first.close()  # twice is fine
    assert_clean(si)


def test_a_non_finite_control_is_refused_and_never_sent():
    si, be = make()
    route = be.single_turn_routes("town_a")[0]
    with be.make_env("town_a", route, "ClearNoon", renderer=False) as env:
        env.reset()
        sent = len(si.controls())
        for kwargs in ({"steer": float("nan"), "target_speed_kmh": 10.0}, {"steer": 0.0, "target_speed_kmh": float("nan")},
                       {"steer": 0.0, "throttle": float("inf"), "brake": 0.0}):
            with pytest.raises(ValueError) as err:
                env.step(**kwargs)
            assert "nan" in str(err.value) or "inf" in str(err.value), err.value  # the value refused
        assert len(si.controls()) == sent
    assert_clean(si)


@pytest.mark.parametrize("wheelbase,max_steer", [(2.87, 70.0), (2.5, 50.0)])
def test_steering_drives_the_reference_curvature_on_the_spawned_car(wheelbase, max_steer):
    si, be = make(wheelbase=wheelbase, max_steer_deg=max_steer)
    route = be.single_turn_routes("town_a")[0]
    ref = VehicleParams()
    with be.make_env("town_a", route, "ClearNoon", renderer=False, endless=True) as env:
        env.reset()
        g = env.geometry
        assert g.wheelbase == pytest.approx(wheelbase, abs=1e-3) and g.max_steer_deg == pytest.approx(max_steer)
        poses = []
        for _ in range(30):
            obs, _, _ = env.step(0.4, throttle=0.8, brake=0.0)
            poses.append(obs["pose"])
        assert si.controls()[-1][2] == pytest.approx(steer_for_car(0.4, g))
    p = np.array(poses)
    ds = np.linalg.norm(np.diff(p[:, :2], axis=0), axis=1).sum()
    dyaw = np.unwrap(p[:, 2])[-1] - p[0, 2]
    want = -math.tan(0.4 * math.radians(ref.max_wheel_angle_deg)) / ref.wheelbase  # positive steer = right
    assert ds > 5.0 and dyaw / ds == pytest.approx(want, rel=0.03)
    assert_clean(si)


def test_collision_and_lane_invasion_sensors_reach_the_info():
    si, be = make()
    si.geometric_sensors = False
    route = be.single_turn_routes("town_a")[0]
    with be.make_env("town_a", route, "ClearNoon", renderer=False) as env:
        env.reset()
        f = si.frame
        si.collisions = {f + 2: (500.0, "vehicle.audi.a2"), f + 3: (40.0, "static.prop.bin"),
                         f + 4: (7.0, "walker.pedestrian.0001")}
        si.invasions = {f + 2: 2}
        infos = [env.step(0.0, target_speed_kmh=10.0)[2] for _ in range(5)]
    assert [i["collision_car"] for i in infos] == [0.0, 500.0, 0.0, 0.0, 0.0]
    assert [i["collision_other"] for i in infos] == [0.0, 0.0, 40.0, 0.0, 0.0]
    assert [i["collision_pedestrian"] for i in infos] == [0.0, 0.0, 0.0, 7.0, 0.0]
    assert [i["lane_invasion"] for i in infos] == [0.0, 2.0, 0.0, 0.0, 0.0]
    assert_clean(si)


def test_leaving_the_lane_fires_the_runners_failure_rules():
    si, be = make()
    eps = build_suite(be, ["town_a"], ["ClearNoon"], pairs=[1])
    res = run(eps, ConstantPolicy(steer=-1.0), be, RunnerConfig(workers=1, progress_bar=False, off_road_s=1.0))
    row, traj = res.rows[0], res.trajectories[eps[0].key]
    assert not row["success"] and row["reason"] in ("off_road", "off_route")
    assert traj["opposite_lane"].max() > 0.5 and traj["off_road"].max() > 0.5
    assert row["opposite_lane_fraction"] > 0 and row["offroad_fraction"] > 0
    assert_clean(si)


def test_the_stub_check_catches_a_malformed_call():
    si, _ = make()
    assert si.check_calls() == []
    with pytest.raises(TypeError):
        si.world.tick(1.0, 2)  # World.tick(seconds) takes one argument
    si.client.set_timeout()  # Client.set_timeout(second): autospec cannot tell, the stubs can
    bad = si.check_calls()
    assert any(b.startswith("World.tick") for b in bad) and any(b.startswith("Client.set_timeout") for b in bad)


def test_runner_workers_are_servers_for_carla():
    assert server_specs({"name": "carla", "port": 2000}, [2000, 2002]) == [
        {"name": "carla", "port": 2000}, {"name": "carla", "port": 2002}]
    assert server_specs({"name": "carla"}, "auto") == [{"name": "carla"}]
    assert server_specs({"name": "embedded"}, 4) is None
    with pytest.raises(ValueError) as err:
        server_specs({"name": "carla"}, 3)
    assert (err.value.key, err.value.value) == ("runner.workers", 3) and "[2000,2002]" in str(err.value)  # ports
    with pytest.raises(ValueError) as err:
        server_specs({"name": "embedded"}, [2000, 2002])
    assert (err.value.key, err.value.value) == ("runner.workers", [2000, 2002])
    with pytest.raises(ValueError) as err:
        RunnerConfig(workers=[2000, 2000])
    assert (err.value.key, err.value.value) == ("runner.workers", [2000, 2000])
    assert RunnerConfig(workers=[2000, 2002]).resolve_workers(list(range(5)), True) == 2


def test_a_failing_cleanup_step_is_logged_and_the_others_still_run(caplog):
    si, be = make()
    env = be.make_env("town_a", be.single_turn_routes("town_a")[0], "ClearNoon", cameras=CAMS)
    env.reset()
    first = next(iter(env.sensors.values()))
    first.stop.side_effect = RuntimeError("the sensor is gone")
    with caplog.at_level(logging.WARNING, logger="cicfw.carla_client.backend"):
        env.close()
    assert "1 step(s) failed: stop: the sensor is gone" in caplog.text
    assert_clean(si)  # every actor destroyed all the same
    assert not si.settings.synchronous_mode  # and the world's settings put back
