"""Test a CARLA server with cicfw's CARLA backend in about a minute: ``python -m cicfw.carla_client.check``
(or ``cicfw carla-check``) ``[--host localhost] [--port 2000] [--town Town01] [--timeout 5]``.

Prints ``PASS`` or ``FAIL`` and one line of evidence per guarantee of
``cicfw.carla_client.backend``, then a summary; exit status 0 when nothing failed. What it does, on the
server: loads the town, plans the suite's routes from the server's map, drives one expert episode of
the suite through the runner (three cameras), a full-lock drive across the road and into the oncoming
lane, a drive into a parked car, and one short collection episode (three cameras, CIL files in a
temporary folder); finally it checks that no actor it spawned is left and the world's settings are as
they were. The checks that need no server (route geometry on the real maps, the recording stand-in)
run in cicfw's own tests; docs/simulator.md lists which is which.
"""
from __future__ import annotations

import argparse
import math
import socket
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from cicfw.benchmark.builtin_policies import ExpertPolicy
from cicfw.benchmark.runner import RunnerConfig, drive
from cicfw.benchmark.suite import build_suite, suite_routes
from cicfw.carla_client.backend import CARLA_VERSION, CarlaBackend, CarlaServerUnavailable, connect, import_carla
from cicfw.collect import episode_plan, resolve_config, run_episode
from cicfw.data.cil_hdf5 import check_file
from cicfw.sim.expert import Expert
from cicfw.sim.roadgraph import STRAIGHT_MAX_DEG
from cicfw.sim.vehicle import VehicleParams

#: known facts of CARLA's maps (checked offline on the OpenDRIVE files)
KNOWN_TOWNS = {"Town01": (12, 24, 24, 24), "Town02": (8, 16, 16, 16)}  # junctions, left, right, straight


class Report:
    """Collects and prints one line per check."""

    def __init__(self, out=None) -> None:
        self.out = out or sys.stdout
        self.lines: list[tuple[str, str, str]] = []

    def add(self, status: str, name: str, detail: str) -> None:
        self.lines.append((status, name, detail))
        print(f"{status:<4}  {name}: {detail}", file=self.out, flush=True)

    def check(self, name: str, fn: Callable[[], tuple[bool, str]]) -> bool:
        try:
            ok, detail = fn()
        except Exception as err:  # noqa: BLE001 - a check that raises is a failed check
            ok, detail = False, f"{type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}"
        self.add("PASS" if ok else "FAIL", name, detail)
        return ok

    @property
    def failed(self) -> int:
        return sum(s == "FAIL" for s, _, _ in self.lines)


def _unused_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class _Recorder:
    """Wraps a backend's make_env to record, per step of every episode: the tick's frame id, each
    camera image's frame id, the pose, the steering sent and the settings/weather seen by the world."""

    def __init__(self, backend: Any) -> None:
        self.backend, self.envs, self.steps = backend, [], []
        self._make = backend.make_env
        backend.make_env = self.make_env

    def make_env(self, *args, **kwargs):
        env = self._make(*args, **kwargs)
        self.envs.append(env)
        step, reset = env.step, env.reset
        rec: list[dict] = []
        self.steps.append(rec)

        def reset_and_look(*a, **k):
            obs = reset(*a, **k)
            settings = env.world.get_settings()
            weather = env.world.get_weather()
            env.seen = {"synchronous": bool(settings.synchronous_mode), "dt": settings.fixed_delta_seconds,
                        "weather_ok": weather == getattr(env.carla.WeatherParameters, env.weather),
                        "frame0": env.frame, "image_frames0": dict(env.image_frames)}
            return obs

        def step_and_record(steer, **k):
            before = env.frame
            obs, done, info = step(steer, **k)
            rec.append({"before": before, "frame": info["frame"], "images": dict(env.image_frames),
                        "steer": float(steer), "pose": obs["pose"], "speed": obs["speed_kmh"] / 3.6,
                        "info": info})
            return obs, done, info

        env.reset, env.step = reset_and_look, step_and_record
        return env


def _curvature_match(rec: list[dict]) -> tuple[float, int]:
    """Median relative error between the curvature the car drove and the one cicfw's steering asked
    for (reference car: tan(steer * 40 deg) / 2.7 m, negative = right), allowing a lag of 0-3 steps."""
    ref = VehicleParams()
    pose = np.array([r["pose"] for r in rec], float)
    speed = np.array([r["speed"] for r in rec], float)
    cmd = -np.tan(np.array([r["steer"] for r in rec]) * math.radians(ref.max_wheel_angle_deg)) / ref.wheelbase
    ds = np.linalg.norm(np.diff(pose[:, :2], axis=0), axis=1)
    dyaw = (np.diff(pose[:, 2]) + np.pi) % (2 * np.pi) - np.pi
    drove = np.where(ds > 0.05, dyaw / np.maximum(ds, 1e-9), np.nan)
    best = (math.inf, 0)
    for lag in range(4):
        c = cmd[: len(drove) - lag] if lag else cmd[: len(drove)]
        d = drove[lag:]
        ok = (np.abs(c) > 0.03) & np.isfinite(d) & (speed[lag + 1: lag + 1 + len(d)] > 1.5)
        if ok.sum() < 5:
            continue
        err = float(np.median(np.abs(d[ok] - c[ok]) / np.abs(c[ok])))
        if err < best[0]:
            best = (err, lag)
    return best


def run_checks(host: str = "localhost", port: int = 2000, town: str = "Town01", timeout: float = 5.0,
               client: Any = None, report: Report | None = None, collect_seconds: float = 8.0) -> Report:
    """Run every check against the server at ``host:port`` (or an already connected ``client``)."""
    rep = report or Report()

    try:
        carla = import_carla()
    except ImportError as err:
        rep.add("FAIL", "client", str(err))
        return rep
    rep.add("PASS", "client", f"carla {carla.Client('localhost', port).get_client_version()} imported")

    def no_server() -> tuple[bool, str]:
        p = _unused_port()
        t0 = time.monotonic()
        try:
            connect("127.0.0.1", p, connect_timeout_s=1.0)
        except CarlaServerUnavailable as err:
            dt = time.monotonic() - t0
            msg = str(err)
            return dt < 4.0 and "\n" not in msg, f"port {p} with nothing on it: one line after {dt:.1f} s"
        return False, f"a server answered at 127.0.0.1:{p}?"
    rep.check("error: no server", no_server)

    if client is None:
        try:
            client = connect(host, port, timeout, max(timeout, 60.0), carla)
        except Exception as err:  # noqa: BLE001
            rep.add("FAIL", "server", str(err))
            return rep
    rep.add("PASS", "server", f"{host}:{port} answers, server {client.get_server_version()} = client "
                              f"{client.get_client_version()} (CARLA {CARLA_VERSION} expected)")

    backend = CarlaBackend(host=host, port=port, client=client, sensor_timeout_s=2.0,
                           town_map={"check": town}, weathers=["ClearNoon", "WetCloudySunset"])
    rec = _Recorder(backend)
    world0 = client.get_world()
    settings0 = world0.get_settings()
    before = (bool(settings0.synchronous_mode), settings0.fixed_delta_seconds)
    spawned: list[int] = []
    try:
        _checks_on_server(rep, backend, rec, town, collect_seconds)
    finally:
        backend.close()
        for env in rec.envs:
            spawned += env.spawned_ids
        spawned += getattr(backend, "_check_extra_ids", [])

    def cleanup() -> tuple[bool, str]:
        world = client.get_world()
        left = [a.id for a in world.get_actors(spawned)] if spawned else []
        s = world.get_settings()
        after = (bool(s.synchronous_mode), s.fixed_delta_seconds)
        ok = not left and after[0] == before[0]
        return ok, (f"{len(spawned)} actors spawned, {len(left)} left; settings after: synchronous="
                    f"{after[0]}, fixed_delta={after[1]} (before: {before[0]}, {before[1]})")
    rep.check("cleanup: no actor left, settings restored", cleanup)
    return rep


def _checks_on_server(rep: Report, backend: Any, rec: _Recorder, town: str, collect_seconds: float) -> None:
    routes: list = []

    def map_and_routes() -> tuple[bool, str]:
        t0 = time.monotonic()
        routes.extend(suite_routes(backend, "check"))
        cmap = backend.map("check")
        n = {c: sum(r.meta["command"] == c for r in routes) for c in (3, 4, 5)}
        junctions = len({r.meta["junction"] for r in routes})
        finite = all(np.all(np.isfinite(r.curvature)) and np.all(np.isfinite(Expert(r).profile)) for r in routes)
        carla = backend.carla
        bad_start = 0
        for r in routes:
            x, y, z, yaw = r.meta["spawn"]
            wp = cmap.get_waypoint(carla.Location(x=x, y=y, z=z), project_to_road=False)
            if wp is None or wp.is_junction or abs((wp.transform.rotation.yaw - yaw + 180) % 360 - 180) > 10:
                bad_start += 1
        known = KNOWN_TOWNS.get(town)
        counts_ok = known is None or (junctions, n[3], n[4], n[5]) == known
        return (bool(routes) and finite and bad_start == 0 and counts_ok,
                f"{town} loaded and planned in {time.monotonic() - t0:.1f} s: {len(routes)} routes at {junctions} "
                f"junctions ({n[3]} left / {n[4]} right / {n[5]} straight, |turn| < {STRAIGHT_MAX_DEG:g} deg = "
                f"straight{'' if known is None else f'; expected {known[1]}/{known[2]}/{known[3]}'}), curvature "
                f"and speed targets {'finite' if finite else 'NOT finite'}, {bad_start} starts off their lane")
    if not rep.check("map and routes", map_and_routes):
        return

    class ExpertWithCameras(ExpertPolicy):
        cameras = ("centre", "left", "right")

    pair = next(i for i, r in enumerate(routes) if r.meta["command"] == 3)  # the first left turn
    episodes = [e for e in build_suite(backend, ["check"], ["ClearNoon"]) if e.pair == pair]
    result: dict = {}

    def expert_episode() -> tuple[bool, str]:
        res = drive(episodes, ExpertWithCameras(), backend, RunnerConfig(progress_bar=False))
        row = result["row"] = res.rows[0]
        return row["success"], (f"pair {pair} ({row['route']}, {row['command']}) under ClearNoon with 3 cameras: "
                                f"{row['reason']} in {row['time_s']} s, {row['steps']} steps, off-road "
                                f"{row['offroad_fraction']}, opposite lane {row['opposite_lane_fraction']}")
    if not rep.check("expert episode of the suite", expert_episode):
        return
    env, steps = rec.envs[0], rec.steps[0]

    def sync() -> tuple[bool, str]:
        frames = [env.seen["frame0"]] + [s["frame"] for s in steps]
        gaps = np.diff(frames)
        ok = env.seen["synchronous"] and abs((env.seen["dt"] or 0) - 0.1) < 1e-6 and bool(np.all(gaps == 1))
        return ok, (f"synchronous={env.seen['synchronous']}, fixed_delta_seconds={env.seen['dt']}; "
                    f"{len(steps)} steps advanced the frame id by {frames[-1] - frames[0]} (one tick per step)")
    rep.check("synchronous stepping, one tick per step", sync)

    def frames_matched() -> tuple[bool, str]:
        bad = sum(1 for s in steps for f in s["images"].values() if f != s["frame"])
        bad += sum(1 for f in env.seen["image_frames0"].values() if f != env.seen["frame0"])
        n = sum(len(s["images"]) for s in steps) + len(env.seen["image_frames0"])
        return bad == 0 and n > 0, f"{n} camera images, {bad} not of their tick's frame"
    rep.check("every image is its tick's frame", frames_matched)

    def steering() -> tuple[bool, str]:
        g = env.geometry
        err, lag = _curvature_match(steps)
        return err < 0.3, (f"{g.type_id}: wheelbase {g.wheelbase:.2f} m, max steer {g.max_steer_deg:.0f} deg; driven "
                           f"vs commanded curvature: median error {err:.0%} (lag {lag} steps)")
    rep.check("steering scaled to the spawned car", steering)

    def in_lane() -> tuple[bool, str]:
        worst = {k: max(s["info"][k] for s in steps) for k in
                 ("off_road", "opposite_lane", "collision_other", "collision_car", "collision_pedestrian")}
        return all(v == 0 for v in worst.values()), "worst in the expert episode: " + ", ".join(
            f"{k} {v:g}" for k, v in worst.items())
    rep.check("infractions: none while the expert drives", in_lane)

    def weather() -> tuple[bool, str]:
        return env.seen["weather_ok"], f"world.get_weather() during the episode is ClearNoon: {env.seen['weather_ok']}"
    rep.check("weather per episode", weather)

    # a full-lock left drive from a straight route's start: into the oncoming lane, then off the road
    straight = next(r for r in routes if r.meta["command"] == 5)

    def full_lock() -> tuple[bool, str]:
        e = backend.make_env("check", straight, "WetCloudySunset", cameras=(), renderer=False, endless=True)
        worst = {"opposite_lane": 0.0, "off_road": 0.0, "lane_invasion": 0.0}
        with e:
            e.reset()
            for _ in range(80):
                _, _, info = e.step(-1.0, target_speed_kmh=12.0)
                for k in worst:
                    worst[k] = max(worst[k], info[k])
            w_ok = e.world.get_weather() == backend.carla.WeatherParameters.WetCloudySunset
        ok = all(v > 0 for v in worst.values()) and w_ok
        return ok, (f"8 s at full left lock under WetCloudySunset (weather set: {w_ok}): max opposite_lane "
                    f"{worst['opposite_lane']:.2f}, max off_road {worst['off_road']:.2f}, lane invasions "
                    f"{worst['lane_invasion']:g} in a step")
    rep.check("infractions: opposite lane, off road, lane invasion sensor", full_lock)

    def collision() -> tuple[bool, str]:
        e = backend.make_env("check", straight, "ClearNoon", cameras=(), renderer=False, endless=True)
        hit = 0.0
        with e:
            e.reset()
            carla = backend.carla
            x, y, z, yaw = straight.meta["spawn"]
            a = math.radians(yaw)
            tf = carla.Transform(carla.Location(x=x + 14 * math.cos(a), y=y + 14 * math.sin(a), z=z + 0.3),
                                 carla.Rotation(yaw=yaw))
            parked = e.world.spawn_actor(e.world.get_blueprint_library().find(backend.vehicle), tf)
            backend._check_extra_ids = [int(parked.id)]
            try:
                for _ in range(60):
                    _, _, info = e.step(0.0, target_speed_kmh=15.0)
                    hit = max(hit, info["collision_car"])
            finally:
                parked.destroy()
        return hit > 0, f"drove into a parked {backend.vehicle} 14 m ahead: collision_car impulse {hit:.0f} N s"
    rep.check("infractions: collision sensor", collision)

    def collection() -> tuple[bool, str]:
        cfg = resolve_config({"towns": ["check"], "weathers": ["ClearNoon"], "episodes": 1,
                              "seconds": collect_seconds, "workers": 0,
                              "sim": {"name": "carla", "host": backend.host, "port": backend.port}}, backend=backend)
        ep = episode_plan(cfg)[0]
        with tempfile.TemporaryDirectory(prefix="cicfw-carla-check-") as tmp:
            marker = run_episode(cfg, ep, Path(tmp), backend)
            infos = [check_file(Path(tmp) / f["name"]) for f in marker["files"]]
        n = sum(i.n for i in infos)
        want = int(round(collect_seconds * 10)) * 3
        return n == want and marker["samples"] == want, (
            f"{collect_seconds:g} s with 3 cameras and CIL noise: {len(infos)} CIL file(s), {n} samples "
            f"(expected {want}), commands {marker['commands']}")
    rep.check("collection episode", collection)


def main(argv: list[str] | None = None, client: Any = None) -> int:
    p = argparse.ArgumentParser(prog="python -m cicfw.carla_client.check", description=__doc__.split("\n\n")[0])
    p.add_argument("--host", default="localhost")
    p.add_argument("--port", type=int, default=2000)
    p.add_argument("--town", default="Town01", help="the CARLA map to test on (Town01: known route counts)")
    p.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for the server to answer")
    args = p.parse_args(argv)
    problem = None
    if not 1 <= args.port <= 65535:
        problem = f"--port must be a TCP port 1..65535, got {args.port}"
    elif not (math.isfinite(args.timeout) and args.timeout > 0):
        problem = f"--timeout must be seconds > 0, got {args.timeout:g}"
    elif not args.host.strip():
        problem = "--host must name the server's machine (a host name or an address), got an empty string"
    if problem:
        print(f"cicfw: error: {problem}", file=sys.stderr)
        return 2
    t0 = time.monotonic()
    rep = run_checks(args.host, args.port, args.town, args.timeout, client=client)
    print(f"carla_check: {sum(s == 'PASS' for s, _, _ in rep.lines)} passed, {rep.failed} failed "
          f"({time.monotonic() - t0:.0f} s)", file=rep.out, flush=True)
    return 1 if rep.failed else 0


if __name__ == "__main__":
    from cicfw.core.errors import install_app_handlers

    install_app_handlers()
    sys.exit(main())
