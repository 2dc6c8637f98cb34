"""Simulator backends behind one interface, registered in ``SIM_BACKENDS`` ("embedded", "carla").

A backend is built from its config's kwargs (``conf/sim/<name>.yaml``: ``name:`` + kwargs) and gives
``towns()``, ``weathers()``, ``single_turn_routes(town)`` and ``make_env(town, route, weather, seed,
cameras, renderer) -> env`` where env has ``reset() -> obs``, ``step(steer, target_speed_kmh=...) ->
(obs, done, info)`` and ``expert_action()``, as ``cicfw.sim.env.DrivingEnv``. The data collector
(``cicfw.sim.collection``) needs a little more: ``random_route``, ``make_env(..., expert=, time_offset=,
endless=)`` and optionally ``resolve_town``; its module docstring lists the whole interface.
"""
from __future__ import annotations

import math
import queue
from pathlib import Path
from typing import Any

import numpy as np

from cicfw.registry import SIM_BACKENDS
from cicfw.sim.roadgraph import COMMAND_DISTANCE, Route, single_turn_routes
from cicfw.sim.town import TownError, load_town, town_names


@SIM_BACKENDS.register("embedded")
class EmbeddedBackend:
    """The simulator shipped with cicfw: towns from ``conf/town``, weathers from ``cicfw.sim.render``."""

    def __init__(self, command_distance: float = COMMAND_DISTANCE, success_radius: float = 2.0,
                 max_deviation: float = 10.0, route_before: float = 30.0, route_after: float = 25.0) -> None:
        self.command_distance = command_distance
        self.success_radius = success_radius
        self.max_deviation = max_deviation
        self.route_before = route_before
        self.route_after = route_after

    def towns(self) -> list[str]:
        return town_names()

    def weathers(self) -> list[str]:
        from cicfw.sim.render import WEATHERS

        return list(WEATHERS)

    def single_turn_routes(self, town: str) -> list[Route]:
        return single_turn_routes(load_town(town), self.route_before, self.route_after, self.command_distance)

    def resolve_town(self, town: str) -> str:
        """A shipped town's name as it is, or a town file's absolute path (the file is loaded and
        checked); a TownError naming the shipped towns, the missing file or the file's problem."""
        s = str(town)
        if s.endswith((".yaml", ".yml")) or "/" in s or "\\" in s:
            p = Path(s).expanduser()
            if not p.is_file():
                raise TownError(f"no such town file: {s!r} (a town is a shipped name: "
                                f"{', '.join(town_names())}, or the path to a town .yaml file)")
            try:
                load_town(p)
            except TownError as err:  # YAML's own messages span lines: keep the error to one
                raise TownError(" ".join(str(err).split())) from None
            return str(p.resolve())
        load_town(s)  # an unknown name raises a TownError naming the shipped towns
        return s

    def random_route(self, town: str, rng: np.random.Generator, min_length: float, name: str = "random",
                     command_distance: float | None = None) -> Route:
        """A random multi-junction route of at least ``min_length`` m (turns balanced within it)."""
        from cicfw.sim.roadgraph import road_graph

        cd = self.command_distance if command_distance is None else float(command_distance)
        return road_graph(load_town(town), cd).random_route(rng, min_length=min_length, name=name, counts={})

    def make_env(self, town: str, route: Route, weather: str, seed: int = 0, cameras: tuple = ("centre",),
                 renderer: bool | Any = True, expert: dict | None = None, time_offset: float = 0.0,
                 endless: bool = False):
        """``expert``: ExpertParams overrides; ``time_offset``: shifts the renderer's clock (rain phase);
        ``endless``: the episode never ends by itself (no success, timeout or lost), for collection."""
        from cicfw.sim.env import DrivingEnv
        from cicfw.sim.expert import ExpertParams

        stop = (dict(timeout=1e9, max_deviation=1e9, success_radius=-1.0) if endless else
                dict(success_radius=self.success_radius, max_deviation=self.max_deviation))
        return DrivingEnv(load_town(town), route, weather=weather, seed=seed, cameras=cameras,
                          renderer=renderer, expert=ExpertParams(**(expert or {})), time_offset=time_offset,
                          **stop)


# ------------------------------------------------------------------------------------------------
# CARLA (0.9.16 Python API). Needs `pip install cicfw[carla]` and a running CARLA server; it cannot be
# exercised without one, so it is kept thin: connect, load the map, set the weather, spawn the car,
# attach three RGB cameras at CIL's mounts, step synchronously at 10 Hz.

CARLA_CAMERAS = {"centre": 0.0, "left": -30.0, "right": 30.0}  # yaw, degrees (positive right)
ROAD_OPTION_TO_CIL = {"LANEFOLLOW": 2, "LEFT": 3, "RIGHT": 4, "STRAIGHT": 5,
                      "CHANGELANELEFT": 2, "CHANGELANERIGHT": 2, "VOID": 2}


def _import_carla():
    try:
        import carla  # noqa: F401
    except ImportError:
        raise ImportError(
            "the 'carla' simulator backend needs the CARLA Python API: pip install cicfw[carla] "
            "(carla==0.9.16), and a CARLA 0.9.16 server running (./CarlaUE4.sh) that host:port in "
            "conf/sim/carla.yaml reaches; or use sim=embedded"
        ) from None
    return carla


@SIM_BACKENDS.register("carla")
class CarlaBackend:
    """Drive real CARLA towns. ``town_map`` maps cicfw town roles to CARLA maps (town_a -> Town01...)."""

    def __init__(self, host: str = "localhost", port: int = 2000, timeout_s: float = 20.0,
                 town_map: dict | None = None, weathers: list | None = None,
                 route_before: float = 30.0, route_after: float = 25.0,
                 success_radius: float = 2.0, max_deviation: float = 10.0) -> None:
        self.carla = _import_carla()
        self.host, self.port, self.timeout_s = host, port, timeout_s
        self.town_map = dict(town_map or {"town_a": "Town01", "town_b": "Town02"})
        self._weathers = list(weathers or ["ClearNoon", "ClearSunset", "MidRainyNoon", "WetCloudySunset"])
        self.route_before, self.route_after = route_before, route_after
        self.success_radius, self.max_deviation = success_radius, max_deviation
        self.client = self.carla.Client(host, port)
        self.client.set_timeout(timeout_s)
        try:
            self.client.get_server_version()
        except RuntimeError as err:
            raise RuntimeError(f"no CARLA server answers at {host}:{port} ({err}); start CARLA 0.9.16 "
                               f"first, or use sim=embedded") from None

    def towns(self) -> list[str]:
        return list(self.town_map)

    def weathers(self) -> list[str]:
        return list(self._weathers)

    def _world(self, town: str):
        carla_town = self.town_map.get(town, town)
        world = self.client.get_world()
        if not world.get_map().name.endswith(carla_town):
            world = self.client.load_world(carla_town)
        return world

    def single_turn_routes(self, town: str) -> list[Route]:
        """One route per junction lane of the CARLA map (each manoeuvre at each junction): start
        ``route_before`` m before the junction, goal ``route_after`` m after it."""
        cmap = self._world(town).get_map()
        routes = []
        for wp_a, wp_b in cmap.get_topology():
            if not wp_a.is_junction:
                continue  # keep the lanes inside junctions: one per manoeuvre
            before = wp_a.previous(self.route_before)
            start = before[0] if before else wp_a
            pts = _walk(start, wp_a) + _walk(wp_a, wp_b)
            after = wp_b.next(self.route_after)
            pts += _walk(wp_b, after[0] if after else wp_b)
            yaw_in = math.radians(wp_a.transform.rotation.yaw)
            yaw_out = math.radians(wp_b.transform.rotation.yaw)
            turn = (yaw_out - yaw_in + math.pi) % (2 * math.pi) - math.pi  # CARLA yaw is clockwise
            code = 5 if abs(turn) < math.radians(45) else (4 if turn > 0 else 3)
            name = f"{town}/{wp_a.get_junction().id}/{wp_a.road_id}:{wp_a.lane_id}/{'?flrs'[code - 1]}"
            routes.append(_carla_route(pts, code, name, wp_a.transform.location, wp_b.transform.location))
        return sorted(routes, key=lambda r: r.name)

    def make_env(self, town: str, route: Route, weather: str, seed: int = 0, cameras: tuple = ("centre",),
                 renderer: bool | Any = True):
        return CarlaEnv(self, self._world(town), route, weather, seed, cameras)


def _walk(a, b, step: float = 0.5, max_n: int = 2000) -> list:
    """Waypoints from ``a`` along its lane (first branch) until within a step of ``b``."""
    out = [a]
    while out[-1].transform.location.distance(b.transform.location) > step and len(out) < max_n:
        nxt = out[-1].next(step)
        if not nxt:
            break
        out.append(min(nxt, key=lambda w: w.transform.location.distance(b.transform.location)))
    return out


def _carla_route(wps: list, code: int, name: str, entry_loc, exit_loc) -> Route:
    """A cicfw Route from CARLA waypoints (coordinates mirrored to our right-handed frame: y -> -y)."""
    pts = np.array([[w.transform.location.x, -w.transform.location.y] for w in wps], float)
    d = np.gradient(pts, axis=0)
    heading = np.arctan2(d[:, 1], d[:, 0])
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    ent = np.array([entry_loc.x, -entry_loc.y])
    ext = np.array([exit_loc.x, -exit_loc.y])
    s_in = s[int(np.argmin(np.linalg.norm(pts - ent, axis=1)))]
    s_out = s[int(np.argmin(np.linalg.norm(pts - ext, axis=1)))]
    cmds = np.full(len(pts), 2, np.int8)
    cmds[(s >= s_in - COMMAND_DISTANCE) & (s <= s_out)] = code
    curv = np.gradient(np.unwrap(heading), s) if len(s) > 2 else np.zeros(len(s))
    return Route(name=name, points=pts, heading=heading, s=s, curvature=curv, commands=cmds,
                 in_junction=(s >= s_in) & (s <= s_out), lanes=(), turns=(("carla", code, s_in, s_out),),
                 meta={"command": code})


class CarlaEnv:
    """One episode in CARLA, synchronous at 10 Hz, same API as DrivingEnv (not testable here)."""

    def __init__(self, backend: CarlaBackend, world, route: Route, weather: str, seed: int,
                 cameras: tuple) -> None:
        from cicfw.sim.expert import Expert
        from cicfw.sim.vehicle import SpeedController

        carla = backend.carla
        self.carla, self.world, self.route, self.backend = carla, world, route, backend
        if not hasattr(carla.WeatherParameters, weather):
            raise ValueError(f"unknown CARLA weather {weather!r}; CARLA presets include ClearNoon, "
                             f"ClearSunset, MidRainyNoon, WetCloudySunset, ...")
        self.weather, self.seed, self.cameras = weather, seed, tuple(cameras)
        for c in self.cameras:
            if c not in CARLA_CAMERAS:
                raise ValueError(f"unknown camera {c!r}; known: {', '.join(CARLA_CAMERAS)}")
        self.expert = Expert(route)
        self.speed_ctl = SpeedController()
        self.actors: list = []
        self.queues: dict = {}
        self.t, self.done = 0.0, False

    def _cleanup(self) -> None:
        for a in self.actors:
            try:
                a.destroy()
            except RuntimeError:
                pass
        self.actors, self.queues = [], {}

    def reset(self) -> dict:
        carla = self.carla
        self._cleanup()
        settings = self.world.get_settings()
        settings.synchronous_mode = True
        settings.fixed_delta_seconds = 0.1
        self.world.apply_settings(settings)
        self.world.set_weather(getattr(carla.WeatherParameters, self.weather))
        bp = self.world.get_blueprint_library()
        car_bp = bp.find("vehicle.lincoln.mkz_2020") if bp.filter("vehicle.lincoln.mkz_2020") else bp.filter("vehicle.*")[0]
        x, y, yaw = self.route.start_pose
        tf = carla.Transform(carla.Location(x=x, y=-y, z=0.5), carla.Rotation(yaw=-math.degrees(yaw)))
        self.car = self.world.spawn_actor(car_bp, tf)
        self.actors.append(self.car)
        # the expert's steering scale must be this car's: CARLA cars steer up to ~70 deg, ours 40
        try:
            from cicfw.sim.expert import Expert
            from cicfw.sim.vehicle import VehicleParams

            wheels = self.car.get_physics_control().wheels
            max_deg = float(wheels[0].max_steer_angle)
            wheelbase = wheels[0].position.distance(wheels[2].position) / 100.0  # front-left to rear-left, cm -> m
            if not 1.5 < wheelbase < 5.0:
                wheelbase = 2.9
            self.expert = Expert(self.route, vehicle=VehicleParams(wheelbase=wheelbase, max_wheel_angle_deg=max_deg))
        except (RuntimeError, IndexError, AttributeError):
            pass
        cam_bp = bp.find("sensor.camera.rgb")
        cam_bp.set_attribute("image_size_x", "800")
        cam_bp.set_attribute("image_size_y", "600")
        cam_bp.set_attribute("fov", "100")
        for name in self.cameras:
            mount = carla.Transform(carla.Location(x=2.0, z=1.4), carla.Rotation(pitch=-15.0, yaw=CARLA_CAMERAS[name]))
            cam = self.world.spawn_actor(cam_bp, mount, attach_to=self.car)
            q: queue.Queue = queue.Queue()
            cam.listen(q.put)
            self.actors.append(cam)
            self.queues[name] = q
        self.t, self.done = 0.0, False
        self.world.tick()
        return self._obs()

    def _images(self) -> dict:
        import cv2

        out = {}
        for name, q in self.queues.items():
            img = q.get(timeout=self.backend.timeout_s)
            a = np.frombuffer(img.raw_data, np.uint8).reshape(img.height, img.width, 4)[:, :, 2::-1]
            out[name] = cv2.resize(np.ascontiguousarray(a[115:510]), (200, 88), interpolation=cv2.INTER_AREA)
        return out

    def _state(self):
        from cicfw.sim.vehicle import VehicleState

        tf = self.car.get_transform()
        v = self.car.get_velocity()
        return VehicleState(tf.location.x, -tf.location.y, -math.radians(tf.rotation.yaw),
                            speed=math.hypot(v.x, v.y))

    def _obs(self) -> dict:
        s = self._state()
        i = self.expert.locate(s.x, s.y)
        return {"images": self._images(), "speed_kmh": s.speed * 3.6, "command": int(self.route.commands[i]),
                "pose": (s.x, s.y, s.yaw), "t": self.t,
                "target_speed_kmh": float(self.expert.profile[min(i + 4, len(self.expert.profile) - 1)]) * 3.6}

    def expert_action(self) -> tuple[float, float]:
        steer, v = self.expert.act(self._state())
        return steer, v * 3.6

    def step(self, steer: float, target_speed_kmh: float | None = None, throttle: float | None = None,
             brake: float | None = None):
        s = self._state()
        if target_speed_kmh is not None:
            throttle, brake = self.speed_ctl(s.speed, target_speed_kmh / 3.6)
        self.car.apply_control(self.carla.VehicleControl(steer=float(steer), throttle=float(throttle or 0.0),
                                                         brake=float(brake or 0.0)))
        self.world.tick()
        self.t += 0.1
        obs = self._obs()
        s = self._state()
        gx, gy = self.route.goal
        dist = math.hypot(gx - s.x, gy - s.y)
        i = self.expert.locate(s.x, s.y)
        dev = float(np.hypot(*(self.route.points[i] - (s.x, s.y))))
        reason = ("success" if dist <= self.backend.success_radius else
                  "timeout" if self.t >= self.route.timeout() else
                  "lost" if dev > self.backend.max_deviation else None)
        self.done = reason is not None
        if self.done:
            self._cleanup()
        info = {"distance_to_goal": dist, "route_deviation": dev, "progress": float(self.route.s[i] / self.route.length),
                "opposite_lane": 0.0, "off_road": 0.0, "in_junction": bool(self.route.in_junction[i]),
                "success": reason == "success", "reason": reason, "t": self.t}
        return obs, self.done, info
