"""The CARLA backend (registry name ``carla``, ``conf/sim/carla.yaml``): CARLA 0.9.16 behind the same
interface as the embedded simulator (``cicfw.sim.backends``).

Needs the client (``pip install "cicfw[carla]"``: carla==0.9.16, Python 3.10-3.12) and a CARLA 0.9.16
server (``./CarlaUE4.sh -carla-rpc-port=2000``). docs/carla.md states its episode model and guarantees
(one episode at a time per server, synchronous frames matched, nothing left behind, infractions in the
embedded simulator's columns, the reference car's steering, one-line errors); tests/test_carla_*.py drive
them offline against a recording stand-in server (``tests/carla_standin.py``).
"""
from __future__ import annotations

import logging
import math
import queue
import re
import time
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from cicfw.carla_client.routes import random_route, single_turn_routes
from cicfw.core.errors import CicfwError
from cicfw.registry import SIM_BACKENDS
from cicfw.sim.backends import positive_distances
from cicfw.sim.episode import step_info
from cicfw.sim.expert import Expert, ExpertParams
from cicfw.sim.roadgraph import COMMAND_DISTANCE, Route
from cicfw.sim.vehicle import DT, SpeedController, VehicleParams, VehicleState

log = logging.getLogger(__name__)

CARLA_VERSION = "0.9.16"
INSTALL_COMMAND = 'pip install "cicfw[carla]"   (= pip install carla==0.9.16; Python 3.10-3.12)'
#: camera name -> yaw (deg, positive right), CIL's mounts
CARLA_CAMERAS = {"centre": 0.0, "left": -30.0, "right": 30.0}
CAMERA_MOUNT = {"x": 2.0, "z": 1.4, "pitch": -15.0}  # m ahead of / above the car's origin, deg
CAMERA_SIZE = (800, 600, 100.0)  # px, px, horizontal FOV deg; cropped to rows 115:510, resized to 200x88
DEFAULT_WEATHERS = ("ClearNoon", "ClearSunset", "MidRainyNoon", "WetCloudySunset")


class CarlaError(RuntimeError, CicfwError):
    """A CARLA problem a user can fix (server, version, package, config); the apps print it as one line."""


class CarlaNotInstalled(CarlaError, ImportError):
    """The ``carla`` client package is missing."""


class CarlaServerUnavailable(CarlaError):
    """No CARLA server answered in time."""


class CarlaVersionMismatch(CarlaError):
    """The server's and the client's CARLA versions differ."""


class CarlaSensorTimeout(CarlaError):
    """A sensor sent nothing for the frame just ticked."""


class CarlaBusy(CarlaError):
    """A second episode on a server that already runs one."""


def import_carla():
    """The ``carla`` module, or one line saying how to install it."""
    try:
        import carla
    except ImportError:
        raise CarlaNotInstalled(f"sim=carla needs the CARLA {CARLA_VERSION} Python client, which is not "
                                f"installed: {INSTALL_COMMAND}; or use sim=embedded") from None
    return carla


def _base_version(v: str) -> str:
    m = re.match(r"\d+(?:\.\d+)*", str(v).strip())
    return m.group(0) if m else str(v).strip()


def connect(host: str = "localhost", port: int = 2000, connect_timeout_s: float = 5.0,
            timeout_s: float = 60.0, carla: Any = None):
    """A ``carla.Client`` connected to a server of the client's own version.

    Fails within ``connect_timeout_s`` with one line when no server answers, and names both versions
    when they differ. Later calls (map loads, spawns) get ``timeout_s``."""
    carla = carla or import_carla()
    client = carla.Client(host, int(port))
    client.set_timeout(float(connect_timeout_s))
    try:
        server = client.get_server_version()
    except RuntimeError:
        raise CarlaServerUnavailable(
            f"no CARLA server answered at {host}:{port} within {connect_timeout_s:g} s "
            f"(sim.connect_timeout_s): start CARLA {CARLA_VERSION} there (./CarlaUE4.sh "
            f"-carla-rpc-port={port}), point sim.host / sim.port at it, or use sim=embedded") from None
    mine = client.get_client_version()
    if _base_version(server) != _base_version(mine):
        raise CarlaVersionMismatch(
            f"the CARLA server at {host}:{port} runs {server} but the carla client is {mine}: run a "
            f"{mine} server, or install the server's client (pip install carla=={_base_version(server)})")
    client.set_timeout(float(timeout_s))
    return client


# ------------------------------------------------------------------------------------------------
# the spawned car's steering


@dataclass(frozen=True)
class CarGeometry:
    """What the env needs of the spawned car (from ``get_physics_control()`` and its bounding box)."""

    type_id: str
    wheelbase: float  # m, front to rear axle
    max_steer_deg: float  # the front wheels' maximum steer angle
    rear_offset: float  # m from the actor's origin to the rear axle, along its heading (< 0: behind)
    half_width: float  # m


def car_geometry(vehicle: Any, transform: Any) -> CarGeometry:
    """The car's steering geometry. Wheel positions come in world coordinates (centimetres in CARLA
    0.9.x; metres are recognised too); index 0/1 are the front wheels, 2/3 the rear ones."""
    type_id = str(getattr(vehicle, "type_id", "vehicle"))
    wheels = list(vehicle.get_physics_control().wheels)
    if len(wheels) < 4:
        raise CarlaError(f"spawned car {type_id} reports {len(wheels)} wheels in get_physics_control(); "
                         f"cicfw needs a four-wheeled car (sim.vehicle)")
    p = np.array([[w.position.x, w.position.y] for w in wheels[:4]], float)
    front, rear = p[:2].mean(axis=0), p[2:4].mean(axis=0)
    scale = 0.01 if np.linalg.norm(front - rear) > 50.0 else 1.0  # cm (CARLA 0.9.x) or m
    front, rear = front * scale, rear * scale
    wheelbase = float(np.linalg.norm(front - rear))
    max_steer = float(max(wheels[0].max_steer_angle, wheels[1].max_steer_angle))
    if not (1.0 < wheelbase < 6.0) or not (5.0 < max_steer < 89.0):
        raise CarlaError(f"spawned car {type_id}: implausible steering geometry from get_physics_control() "
                         f"(wheelbase {wheelbase:.2f} m, max steer {max_steer:.1f} deg); choose another sim.vehicle")
    yaw = math.radians(transform.rotation.yaw)
    fwd = np.array([math.cos(yaw), math.sin(yaw)])
    loc = np.array([transform.location.x, transform.location.y])
    rear_offset = float(np.dot(rear - loc, fwd))
    if abs(rear_offset) > wheelbase:
        rear_offset = -wheelbase / 2  # positions not in the world frame: assume the origin mid-wheelbase
    half_width = float(vehicle.bounding_box.extent.y) if hasattr(vehicle, "bounding_box") else 0.9
    return CarGeometry(type_id, wheelbase, max_steer, rear_offset, half_width if half_width > 0.3 else 0.9)


def steer_for_car(steer: float, car: CarGeometry, ref: VehicleParams | None = None) -> float:
    """cicfw steering (the reference car's) -> CARLA steering for ``car``: the same path curvature."""
    ref = ref or VehicleParams()
    curvature = math.tan(float(steer) * math.radians(ref.max_wheel_angle_deg)) / ref.wheelbase
    angle = math.atan(curvature * car.wheelbase)
    return float(min(max(angle / math.radians(car.max_steer_deg), -1.0), 1.0))


# ------------------------------------------------------------------------------------------------
# the backend


@SIM_BACKENDS.register("carla")
class CarlaBackend:
    """CARLA towns behind the backend interface. ``town_map`` maps cicfw town roles to CARLA maps
    (``town_a`` -> Town01, ``town_b`` -> Town02); a CARLA map name works as a town too.

    ``client``: an already connected ``carla.Client`` (or a stand-in); otherwise one is connected to
    ``host:port`` on first use (``connect``)."""

    #: one world per server: episodes run one after another, ``runner.workers`` is a list of ports
    lockstep = False
    #: the collected data's ``sim_version`` (metadata): bump when what the env records changes
    data_version = f"carla-{CARLA_VERSION}-1"

    def __init__(self, host: str = "localhost", port: int = 2000, connect_timeout_s: float = 5.0,
                 timeout_s: float = 60.0, tick_timeout_s: float = 10.0, sensor_timeout_s: float = 2.0,
                 town_map: dict | None = None, weathers: list | None = None,
                 vehicle: str = "vehicle.lincoln.mkz_2020", settle_ticks: int = 5,
                 route_before: float = 30.0, route_after: float = 25.0,
                 command_distance: float = COMMAND_DISTANCE, success_radius: float = 2.0,
                 max_deviation: float = 10.0, ports: list | None = None, client: Any = None) -> None:
        self.carla = import_carla()
        self.host, self.port = host, int(port)
        self.connect_timeout_s, self.timeout_s = float(connect_timeout_s), float(timeout_s)
        self.tick_timeout_s, self.sensor_timeout_s = float(tick_timeout_s), float(sensor_timeout_s)
        for key, v in (("connect_timeout_s", self.connect_timeout_s), ("timeout_s", self.timeout_s),
                       ("tick_timeout_s", self.tick_timeout_s), ("sensor_timeout_s", self.sensor_timeout_s)):
            if not v > 0:
                raise CarlaError(f"sim.{key} must be > 0 seconds, got {v}")
        self.town_map = dict(town_map or {"town_a": "Town01", "town_b": "Town02"})
        self._weathers = list(weathers or DEFAULT_WEATHERS)
        presets = sorted(n for n in dir(self.carla.WeatherParameters) if n[:1].isupper())
        for w in self._weathers:
            if w not in presets:
                raise CarlaError(f"sim.weathers: {w!r} is no CARLA weather preset; presets: {', '.join(presets)}")
        self.vehicle = str(vehicle)
        self.settle_ticks = int(settle_ticks)
        (self.route_before, self.route_after, self.command_distance, self.success_radius,
         self.max_deviation) = positive_distances(route_before=route_before, route_after=route_after,
                                                  command_distance=command_distance,
                                                  success_radius=success_radius, max_deviation=max_deviation)
        self.ports = [int(p) for p in ports] if ports else None  # collection: one worker per server
        self._client = client
        self._maps: dict[str, Any] = {}
        self._live: CarlaEnv | None = None

    # -- connection, worlds, maps
    @property
    def client(self):
        if self._client is None:
            self._client = connect(self.host, self.port, self.connect_timeout_s, self.timeout_s, self.carla)
        return self._client

    def carla_town(self, town: str) -> str:
        return str(self.town_map.get(town, town))

    def world(self, town: str):
        """The server's world with ``town``'s map loaded (``load_world`` only when another is loaded)."""
        name = self.carla_town(town)
        world = self.client.get_world()
        if world.get_map().name.rsplit("/", 1)[-1] != name:
            if self._live is not None:
                raise CarlaBusy(f"cannot load {name} while an episode runs on {self.host}:{self.port}")
            self._check_map(self.client, self.port, name, f"town {town!r}: ")
            log.info("CARLA %s:%d: loading %s", self.host, self.port, name)
            world = self.client.load_world(name)
        return world

    def map(self, town: str):
        """The ``carla.Map`` of ``town`` (cached)."""
        name = self.carla_town(town)
        if name not in self._maps:
            self._maps[name] = self.world(town).get_map()
        return self._maps[name]

    # -- the backend interface
    def towns(self) -> list[str]:
        return list(self.town_map)

    def weathers(self) -> list[str]:
        return list(self._weathers)

    def single_turn_routes(self, town: str) -> list[Route]:
        """One route per lane through a junction of the CARLA map (``cicfw.carla_client.routes``)."""
        return single_turn_routes(self.map(town), town, self.route_before, self.route_after,
                                  self.command_distance)

    def resolve_town(self, town: str) -> str:
        """A town role (``town_a``) or a mapped CARLA map name (``Town01``) as it is; else one error
        naming them (the server's own list is checked when the map is loaded)."""
        known = list(self.town_map) + [v for v in self.town_map.values() if v not in self.town_map]
        if str(town) not in known:
            raise CarlaError(f"unknown CARLA town {town!r}; known: {', '.join(known)} (sim.town_map maps "
                             f"cicfw towns to CARLA maps)")
        self.check_servers(self.carla_town(town))
        return str(town)

    def check_servers(self, carla_town: str | None = None) -> None:
        """Connect now to the server (and to every one in ``ports``) and check it has ``carla_town``:
        the one-line errors come before anything is written or simulated."""
        ports = [self.port] + [p for p in (self.ports or []) if p != self.port]
        clients = [self.client] + [connect(self.host, p, self.connect_timeout_s, self.timeout_s, self.carla)
                                   for p in ports[1:]]
        if carla_town is None:
            return
        for port, client in zip(ports, clients):
            self._check_map(client, port, carla_town)

    def _check_map(self, client: Any, port: int, name: str, where: str = "") -> None:
        """One ``CarlaError`` when the server at ``port`` has no map ``name``, listing the maps it has."""
        available = [m.rsplit("/", 1)[-1] for m in client.get_available_maps()]
        if name not in available:
            raise CarlaError(f"{where}map {name!r} is not on the CARLA server at {self.host}:{port}; it has "
                             f"{', '.join(sorted(available))} (sim.town_map)")

    def random_route(self, town: str, rng: np.random.Generator, min_length: float, name: str = "random",
                     command_distance: float | None = None, counts: dict | None = None) -> Route:
        """A multi-junction route for data collection, from a random point of a driving lane; turns
        drawn to stay balanced (within the route, or across routes through a shared ``counts``)."""
        cd = self.command_distance if command_distance is None else float(command_distance)
        return random_route(self.map(town), rng, min_length, name, {} if counts is None else counts, cd)

    def make_env(self, town: str, route: Route, weather: str, seed: int = 0, cameras: tuple = ("centre",),
                 renderer: bool | Any = True, expert: dict | None = None, time_offset: float = 0.0,
                 endless: bool = False) -> "CarlaEnv":
        """An episode (nothing is spawned until ``reset``). ``renderer`` false: no cameras at all;
        ``expert``: ExpertParams overrides; ``endless``: the episode never ends by itself (no success,
        timeout or lost), for collection; ``time_offset`` has no meaning in CARLA (ignored)."""
        stop = dict(timeout=1e9, max_deviation=1e9, success_radius=-1.0) if endless else {}
        return CarlaEnv(self, town, route, weather, seed, tuple(cameras) if renderer else (),
                        expert=ExpertParams(**(expert or {})), **stop)

    @staticmethod
    def worker_kwargs(kwargs: dict, index: int) -> dict | None:
        """The kwargs of collection worker ``index``: one server each, ``port = ports[index]`` when
        ``ports`` lists several (``sim.ports=[2000,2002]``); a single server takes one worker only."""
        ports = kwargs.get("ports") or [kwargs.get("port", 2000)]
        if index >= len(ports):
            return None
        return {**{k: v for k, v in kwargs.items() if k != "ports"}, "port": int(ports[index])}

    # -- one live episode per server
    def _claim(self, env: "CarlaEnv") -> None:
        if self._live is not None and self._live is not env:
            raise CarlaBusy(f"the CARLA server at {self.host}:{self.port} already runs an episode "
                            f"({self._live.route.name}); CARLA runs one episode at a time per server: close "
                            f"it first, or give runner.workers a list of ports (one server each)")
        self._live = env

    def _release(self, env: "CarlaEnv") -> None:
        if self._live is env:
            self._live = None

    def close(self) -> None:
        """Close the live episode, if any (actors destroyed, settings restored)."""
        if self._live is not None:
            self._live.close()

    def __enter__(self) -> "CarlaBackend":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# ------------------------------------------------------------------------------------------------
# one episode


class CarlaEnv:
    """One episode in CARLA with ``cicfw.sim.env.DrivingEnv``'s API: ``reset() -> obs``, ``step(steer,
    target_speed_kmh=... | throttle=..., brake=...) -> (obs, done, info)``, ``expert_action()``; plus
    ``close()`` and ``with env:``. Actors exist from ``reset`` until the episode ends or ``close``."""

    def __init__(self, backend: CarlaBackend, town: str, route: Route, weather: str, seed: int = 0,
                 cameras: tuple = ("centre",), expert: Any = None, success_radius: float | None = None,
                 max_deviation: float | None = None, timeout: float | None = None) -> None:
        self.backend, self.carla, self.town, self.route = backend, backend.carla, town, route
        if weather not in backend.weathers() and not hasattr(self.carla.WeatherParameters, weather):
            raise CarlaError(f"unknown CARLA weather {weather!r}; configured: {', '.join(backend.weathers())}")
        self.weather, self.seed, self.cameras = weather, int(seed), tuple(cameras)
        for c in self.cameras:
            if c not in CARLA_CAMERAS:
                raise CarlaError(f"unknown camera {c!r}; known: {', '.join(CARLA_CAMERAS)}")
        self.expert_params = expert or ExpertParams()
        self.success_radius = backend.success_radius if success_radius is None else float(success_radius)
        self.max_deviation = backend.max_deviation if max_deviation is None else float(max_deviation)
        self._timeout = timeout
        self.vehicle_params = VehicleParams()  # the reference car cicfw's steering refers to
        self.speed_ctl = SpeedController(params=self.vehicle_params)
        self.world = self.map = self.car = self.geometry = None
        self.expert = None
        self.actors: list = []
        self.sensors: dict[str, Any] = {}
        self.queues: dict[str, queue.Queue] = {}
        self._saved_settings = None
        self._pending: dict[str, list] = {"collision": [], "lane_invasion": []}
        self._state: VehicleState | None = None
        self.frame = -1
        self.images: dict[str, np.ndarray] = {}
        self.image_frames: dict[str, int] = {}  # camera -> the frame id its current image carries
        self.spawned_ids: list[int] = []  # every actor this env spawned (for checks after close)
        self.events: dict[str, float] = {}
        self.t, self.steps, self.done, self.live = 0.0, 0, False, False

    @property
    def timeout(self) -> float:
        return self._timeout if self._timeout is not None else self.route.timeout()

    # -- lifecycle
    def __enter__(self) -> "CarlaEnv":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def reset(self, route: Route | None = None) -> dict:
        """Set up the episode (town, synchronous settings, weather, car, sensors) and return the first
        observation. Anything that fails or is interrupted on the way is undone."""
        if self.live:
            self.close()
        if route is not None:
            self.route = route
        carla, be = self.carla, self.backend
        try:
            self.world = be.world(self.town)  # CarlaBusy if another episode runs on another map
            self.map = be.map(self.town)
            be._claim(self)  # CarlaBusy if another episode runs
            self.live, self.done = True, False
            self._saved_settings = self.world.get_settings()
            settings = self.world.get_settings()
            settings.synchronous_mode = True
            settings.fixed_delta_seconds = DT
            self.world.apply_settings(settings)
            self.world.set_weather(getattr(carla.WeatherParameters, self.weather))
            lib = self.world.get_blueprint_library()
            car_bp = lib.find(be.vehicle)
            if car_bp.has_attribute("role_name"):
                car_bp.set_attribute("role_name", "hero")
            (x0, y0), h0 = self.route.points[0], self.route.heading[0]  # without a spawn: the start, CARLA's frame
            x, y, z, yaw = self.route.meta.get("spawn") or (float(x0), float(-y0), 0.0, float(-math.degrees(h0)))
            tf = carla.Transform(carla.Location(x=x, y=y, z=z + 0.3), carla.Rotation(yaw=yaw))
            try:
                self.car = self.world.spawn_actor(car_bp, tf)
            except RuntimeError as err:
                raise CarlaError(f"could not spawn {be.vehicle} at the start of {self.route.name} "
                                 f"(x={x:.1f}, y={y:.1f}): {err}") from None
            self.actors.append(self.car)
            self.spawned_ids.append(int(self.car.id))
            self._spawn_sensors(lib)
            for _ in range(max(be.settle_ticks, 0)):  # let the car settle on its wheels, braked
                self.car.apply_control(carla.VehicleControl(throttle=0.0, steer=0.0, brake=1.0))
                self._tick()
            self.geometry = car_geometry(self.car, self.car.get_transform())
            self.expert = Expert(self.route, self.expert_params, self.vehicle_params)
            self.speed_ctl.reset()
            self._tick()
            self.t, self.steps = 0.0, 0
            return self._obs(self.expert.locate(self._state.x, self._state.y))
        except BaseException:
            self.close()
            raise

    def _spawn_sensors(self, lib: Any) -> None:
        carla = self.carla
        w, h, fov = CAMERA_SIZE
        for name in self.cameras:
            bp = lib.find("sensor.camera.rgb")
            bp.set_attribute("image_size_x", str(w))
            bp.set_attribute("image_size_y", str(h))
            bp.set_attribute("fov", str(fov))
            bp.set_attribute("sensor_tick", "0.0")
            mount = carla.Transform(carla.Location(x=CAMERA_MOUNT["x"], z=CAMERA_MOUNT["z"]),
                                    carla.Rotation(pitch=CAMERA_MOUNT["pitch"], yaw=CARLA_CAMERAS[name]))
            self._attach(name, bp, mount)
        for name, bp_id in (("collision", "sensor.other.collision"), ("lane_invasion", "sensor.other.lane_invasion")):
            self._attach(name, lib.find(bp_id), carla.Transform())

    def _attach(self, name: str, bp: Any, mount: Any) -> None:
        sensor = self.world.spawn_actor(bp, mount, attach_to=self.car)
        self.actors.append(sensor)
        self.spawned_ids.append(int(sensor.id))
        q: queue.Queue = queue.Queue()
        sensor.listen(q.put)
        self.sensors[name], self.queues[name] = sensor, q

    def close(self) -> None:
        """Stop the sensors, destroy every actor this episode spawned, restore the world's settings.
        Safe to call twice; a failing step is logged and the others still run."""
        failures = []
        steps = [("stop", s.stop) for s in self.sensors.values()]
        steps += [("destroy", a.destroy) for a in reversed(self.actors)]
        if self._saved_settings is not None and self.world is not None:
            steps.append(("apply_settings", lambda: self.world.apply_settings(self._saved_settings)))
        for what, step in steps:
            try:
                step()
            except Exception as err:  # noqa: BLE001 - keep cleaning up
                failures.append(f"{what}: {err}")
        self.actors, self.sensors, self.queues = [], {}, {}
        self._saved_settings = None
        self.car = None
        self.live = False
        self.backend._release(self)
        if failures:
            log.warning("CARLA cleanup of %s: %d step(s) failed: %s", self.route.name, len(failures), failures[0])

    # -- stepping
    def _tick(self) -> int:
        """Tick once; collect the snapshot and every sensor's data of exactly that frame."""
        frame = int(self.world.tick(self.backend.tick_timeout_s))
        deadline = time.monotonic() + self.backend.sensor_timeout_s
        snap = self.world.get_snapshot()
        while snap.frame != frame:
            if time.monotonic() > deadline:
                raise CarlaSensorTimeout(f"the world snapshot stayed at frame {snap.frame} after tick() "
                                         f"returned frame {frame} (sim.sensor_timeout_s = "
                                         f"{self.backend.sensor_timeout_s:g} s)")
            time.sleep(0.001)
            snap = self.world.get_snapshot()
        actor = snap.find(self.car.id)
        tf, v = actor.get_transform(), actor.get_velocity()
        self.frame = frame
        self._set_state(tf, v)
        self.images = {name: self._image(name, frame, deadline) for name in self.cameras}
        self.events = self._drain_events(frame)
        return frame

    def _image(self, name: str, frame: int, deadline: float) -> np.ndarray:
        q = self.queues[name]
        while True:
            try:
                data = q.get(timeout=max(deadline - time.monotonic(), 0.0))
            except queue.Empty:
                raise CarlaSensorTimeout(
                    f"camera {name!r} sent no image for frame {frame} within {self.backend.sensor_timeout_s:g} s "
                    f"of the tick (sim.sensor_timeout_s); is the CARLA server overloaded?") from None
            if data.frame < frame:
                continue  # an older frame: drop it
            self.image_frames[name] = int(data.frame)
            if data.frame > frame:
                raise CarlaError(f"camera {name!r} sent frame {data.frame} while frame {frame} was expected: "
                                 f"another client is ticking the server at {self.backend.host}:{self.backend.port}")
            a = np.frombuffer(data.raw_data, np.uint8).reshape(data.height, data.width, 4)
            crop = a[115 * data.height // 600:510 * data.height // 600]  # CIL's rows 115:510 of 600
            small = cv2.resize(crop, (200, 88), interpolation=cv2.INTER_AREA)
            return np.ascontiguousarray(small[:, :, 2::-1])  # BGRA -> RGB

    def _drain_events(self, frame: int) -> dict[str, float]:
        out = {"collision_other": 0.0, "collision_pedestrian": 0.0, "collision_car": 0.0, "lane_invasion": 0.0}
        for name in ("collision", "lane_invasion"):
            q = self.queues.get(name)
            if q is None:
                continue
            while True:
                try:
                    self._pending[name].append(q.get_nowait())
                except queue.Empty:
                    break
            now = [e for e in self._pending[name] if e.frame <= frame]
            self._pending[name] = [e for e in self._pending[name] if e.frame > frame]
            for e in now:
                if name == "lane_invasion":
                    out["lane_invasion"] += len(e.crossed_lane_markings)
                    continue
                imp = e.normal_impulse
                intensity = math.sqrt(imp.x ** 2 + imp.y ** 2 + imp.z ** 2)
                kind = str(getattr(e.other_actor, "type_id", ""))
                key = ("collision_pedestrian" if kind.startswith("walker") else
                       "collision_car" if kind.startswith("vehicle") else "collision_other")
                out[key] += intensity
        return out

    def _set_state(self, tf: Any, v: Any) -> None:
        yaw_c = math.radians(tf.rotation.yaw)
        off = self.geometry.rear_offset if self.geometry is not None else 0.0
        rx, ry = tf.location.x + off * math.cos(yaw_c), tf.location.y + off * math.sin(yaw_c)
        speed = v.x * math.cos(yaw_c) + v.y * math.sin(yaw_c)  # forward speed
        self._centre = tf
        self._state = VehicleState(rx, -ry, -yaw_c, speed=max(float(speed), 0.0))

    def expert_action(self) -> tuple[float, float]:
        """The expert's (steer in cicfw's convention, target speed km/h) for the current state."""
        steer, v = self.expert.act(self._state)
        return steer, v * 3.6

    def step(self, steer: float, target_speed_kmh: float | None = None, throttle: float | None = None,
             brake: float | None = None) -> tuple[dict, bool, dict]:
        if not self.live:
            raise RuntimeError("CarlaEnv.step outside an episode: call reset() first (the episode ended or was closed)")
        s = self._state
        if target_speed_kmh is not None:
            throttle, brake = self.speed_ctl(s.speed, float(target_speed_kmh) / 3.6)
        elif throttle is None:
            raise ValueError("CarlaEnv.step needs target_speed_kmh= or throttle= (and brake=)")
        brake = 0.0 if brake is None else brake
        control = (float(steer), float(throttle), float(brake))
        if not all(math.isfinite(c) for c in control):
            raise ValueError(f"non-finite control for CARLA in {self.route.name} at t={self.t:.1f} s "
                             f"(steer={control[0]}, throttle={control[1]}, brake={control[2]}"
                             f"{'' if target_speed_kmh is None else f', target speed {target_speed_kmh} km/h'}); "
                             f"nothing was sent")
        self.car.apply_control(self.carla.VehicleControl(
            throttle=min(max(control[1], 0.0), 1.0), steer=steer_for_car(control[0], self.geometry),
            brake=min(max(control[2], 0.0), 1.0)))
        self._tick()
        self.t += DT
        self.steps += 1
        i = self.expert.locate(self._state.x, self._state.y)
        obs, info = self._obs(i), self.info(i)
        self.done = info["reason"] is not None
        if self.done:
            self.close()
        return obs, self.done, info

    def _obs(self, i: int) -> dict:
        s = self._state
        return {"images": dict(self.images), "speed_kmh": s.speed * 3.6, "command": int(self.route.commands[i]),
                "pose": (s.x, s.y, s.yaw), "t": self.t, "frame": self.frame,
                "target_speed_kmh": float(self.expert.profile[min(i + 4, len(self.expert.profile) - 1)]) * 3.6}

    def lane_fractions(self) -> tuple[bool, float, float]:
        """(in_junction, opposite-lane fraction, off-road fraction) of the car's width now, from the
        map's driving lanes at five points across the car at its origin (0, 0 inside junctions)."""
        carla, tf = self.carla, self._centre
        yaw = math.radians(tf.rotation.yaw)
        rx, ry = -math.sin(yaw), math.cos(yaw)  # the car's right, CARLA frame
        centre = self.map.get_waypoint(tf.location, project_to_road=False)
        if centre is not None and centre.is_junction:
            return True, 0.0, 0.0
        hw = self.geometry.half_width
        opp = off = 0
        offsets = np.linspace(-hw, hw, 5)
        for d in offsets:
            loc = carla.Location(x=tf.location.x + d * rx, y=tf.location.y + d * ry, z=tf.location.z)
            wp = self.map.get_waypoint(loc, project_to_road=False)
            if wp is None:
                off += 1
            elif math.cos(math.radians(wp.transform.rotation.yaw) - yaw) < 0.0:
                opp += 1
        return False, opp / len(offsets), off / len(offsets)

    def info(self, i: int | None = None) -> dict:
        s = self._state
        if i is None:
            i = self.expert.locate(s.x, s.y)
        info = step_info(self.route, s.x, s.y, i, self.t, self.success_radius, self.timeout, self.max_deviation,
                         self.lane_fractions())
        end = {k: info.pop(k) for k in ("success", "reason", "t")}  # the events sit before them
        return {**info, **self.events, **end, "frame": self.frame}
