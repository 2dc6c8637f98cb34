"""A recording stand-in for a CARLA 0.9.16 server, for tests without one.

Every object the adapter talks to (client, world, blueprints, actors, sensor data, snapshots) is a
``unittest.mock.create_autospec`` of the real class of the installed ``carla`` wheel, so a misspelt
method fails; ``StandIn.check_calls()`` then binds every recorded call to the signatures of the
wheel's own stubs (``carla/libcarla.pyi``), which autospec cannot do for compiled classes. Maps are
the real ``carla.Map`` built from OpenDRIVE files (``maps_dir``/<Town>.xodr), settings, transforms,
controls and physics controls are real ``carla`` objects.

The world behaves as a server would for what cicfw uses: ``tick()`` advances one frame and moves the
cars (a kinematic bicycle with the car's own wheelbase and maximum steer angle, in CARLA's frame),
then every listening sensor gets that frame's data: cameras an 800x600 BGRA image whose colour encodes
the frame id (blue = frame % 256, green = frame // 256 % 256, red = the camera's index), collision and
lane-invasion sensors the events scripted for that frame. ``load_world`` destroys every actor.

``log`` records what happened, in order: ``("tick", frame, weather, synchronous, fixed_delta, town)``,
``("apply_settings", synchronous, fixed_delta)``, ``("weather", name)``, ``("spawn", id, type_id)``,
``("destroy", id)``, ``("control", frame, steer, throttle, brake)``, ``("load_world", name)``.

Faults: ``drop`` (set of frames whose camera images never come), ``backlog`` (each camera also sends
an older frame's image after the current one, and the previous frame's image again before it),
``delay_s`` (images arrive from another thread after this delay), ``on_tick(frame)`` (called before
each tick; may raise, e.g. KeyboardInterrupt), ``collisions`` / ``invasions`` (frame -> event).
"""
from __future__ import annotations

import ast
import functools
import inspect
import math
import os
import threading
from pathlib import Path
from typing import Any, Callable
from unittest import mock

import numpy as np

from cicfw.sim.vehicle import Vehicle, VehicleParams, VehicleState

DT_DEFAULT = 0.05  # what an asynchronous server would advance per tick (never used by cicfw)


def maps_dir() -> Path | None:
    """Where CARLA's OpenDRIVE files for the tests are: ``$CICFW_CARLA_MAPS``, else ``../shared/carla-maps``
    beside the repository (they are test data, never copied into it); None when absent."""
    env = os.environ.get("CICFW_CARLA_MAPS")
    p = Path(env) if env else Path(__file__).resolve().parents[2] / "shared" / "carla-maps"
    return p if (p / "Town01.xodr").is_file() and (p / "Town02.xodr").is_file() else None


# ------------------------------------------------------------------------------------------------
# the wheel's stubs as signatures


@functools.lru_cache(maxsize=1)
def stub_signatures() -> dict[str, tuple[list[str], dict[str, list[inspect.Signature]]]]:
    """class -> (base class names, method -> [signature of each overload]) from carla/libcarla.pyi."""
    import carla

    path = Path(carla.__file__).parent / "libcarla.pyi"
    tree = ast.parse(path.read_text())
    out: dict = {}
    for node in tree.body:
        if not isinstance(node, ast.ClassDef):
            continue
        bases = [b.id for b in node.bases if isinstance(b, ast.Name)]
        methods: dict[str, list[inspect.Signature]] = {}
        for item in node.body:
            if isinstance(item, ast.FunctionDef):
                fn = _signature_of(item)
                if fn is not None:
                    methods.setdefault(item.name, []).append(fn)
        out[node.name] = (bases, methods)
    return out


def _signature_of(node: ast.FunctionDef) -> inspect.Signature | None:
    args = node.args
    for a in args.posonlyargs + args.args + args.kwonlyargs:
        a.annotation = None
    if args.vararg:
        args.vararg.annotation = None
    if args.kwarg:
        args.kwarg.annotation = None
    args.defaults = [ast.Constant(None) for _ in args.defaults]
    args.kw_defaults = [None if d is None else ast.Constant(None) for d in args.kw_defaults]
    fn = ast.FunctionDef(name="f", args=args, body=[ast.Pass()], decorator_list=[], returns=None)
    if "type_params" in ast.FunctionDef._fields:  # Python >= 3.12
        fn.type_params = []
    mod = ast.fix_missing_locations(ast.Module(body=[fn], type_ignores=[]))
    ns: dict = {}
    try:
        exec(compile(mod, "<stub>", "exec"), ns)
    except SyntaxError:
        return None
    return inspect.signature(ns["f"])


def method_signatures(cls_name: str, method: str) -> list[inspect.Signature]:
    """The stub signatures of ``cls_name.method`` (looked up through the stub's base classes)."""
    stubs = stub_signatures()
    todo, seen = [cls_name], set()
    while todo:
        c = todo.pop(0)
        if c in seen or c not in stubs:
            continue
        seen.add(c)
        bases, methods = stubs[c]
        if method in methods:
            return methods[method]
        todo += bases
    return []


# ------------------------------------------------------------------------------------------------
# the stand-in


@functools.lru_cache(maxsize=1)
def client_version() -> str:
    """The installed client's version (the real ``carla.Client`` reports it without a server)."""
    import carla

    return str(carla.Client("localhost", 2000).get_client_version())


class StandIn:
    """A CARLA server stand-in: ``client`` is what ``carla.Client(host, port)`` would return."""

    def __init__(self, maps_dir: str | Path, town: str = "Town01", version: str = "0.9.16",
                 wheelbase: float = 2.87, max_steer_deg: float = 70.0, image_size: tuple = (800, 600),
                 image_size_override: tuple | None = None) -> None:
        import carla

        self.carla = carla
        self.maps_dir = Path(maps_dir)
        self.version = version
        self.wheelbase, self.max_steer_deg = float(wheelbase), float(max_steer_deg)
        self.image_size = image_size  # when a camera blueprint sets no size
        self.image_size_override = image_size_override  # (w, h) every camera sends, whatever was asked (speed)
        self.log: list[tuple] = []
        self.frame = 1000
        self.alive: dict[int, dict] = {}  # actor id -> record
        self._next_id = 100
        self._maps: dict[str, Any] = {}
        self._mocks: list[tuple[Any, str]] = []  # (autospec mock, carla class name) for check_calls
        self.settings = carla.WorldSettings()
        self.weather = "Default"
        self.drop: set[int] = set()
        self.backlog = False
        self.delay_s = 0.0
        self.on_tick: Callable[[int], None] | None = None
        self.collisions: dict[int, tuple[float, str]] = {}
        self.invasions: dict[int, int] = {}
        self.geometric_sensors = True  # also emit events from the geometry (see _geometric_events)
        self.timers: list[threading.Timer] = []
        self.client = self._spec(carla.Client)
        self.client.get_server_version.side_effect = lambda: self.version
        self.client.get_client_version.side_effect = lambda: client_version()
        self.client.get_world.side_effect = lambda: self.world
        self.client.load_world.side_effect = self._load_world
        self.client.get_available_maps.side_effect = lambda: sorted(
            f"/Game/Carla/Maps/{p.stem}" for p in self.maps_dir.glob("*.xodr"))
        self.world = self._make_world(town)

    # -- helpers
    def _spec(self, cls: type) -> Any:
        m = mock.create_autospec(cls, instance=True)
        self._mocks.append((m, cls.__name__))
        return m

    def map(self, name: str):
        if name not in self._maps:
            self._maps[name] = self.carla.Map(name, (self.maps_dir / f"{name}.xodr").read_text())
        return self._maps[name]

    def _copy_settings(self, s: Any) -> Any:
        return self.carla.WorldSettings(synchronous_mode=bool(s.synchronous_mode),
                                        no_rendering_mode=bool(s.no_rendering_mode),
                                        fixed_delta_seconds=float(s.fixed_delta_seconds or 0.0))

    def check_calls(self) -> list[str]:
        """Every call recorded on every stand-in object that binds to none of the stub's signatures
        for that method (as 'Class.method(args)'); [] when all calls are well-formed."""
        bad = []
        for m, cls in self._mocks:
            for name, args, kwargs in m.mock_calls:
                if not name or "." in name or name.startswith("__"):
                    continue
                sigs = method_signatures(cls, name)
                if not sigs:
                    bad.append(f"{cls}.{name}: no such method in the stubs")
                    continue
                for sig in sigs:
                    try:
                        sig.bind(None, *args, **kwargs)
                        break
                    except TypeError:
                        continue
                else:
                    bad.append(f"{cls}.{name}{args}{kwargs}: binds to no stub signature")
        return bad

    # -- the world
    def _make_world(self, town: str) -> Any:
        carla = self.carla
        w = self._spec(carla.World)
        w.town = town
        w.get_map.side_effect = lambda: self._current(w) and self.map(town)
        w.get_settings.side_effect = lambda: self._copy_settings(self.settings)
        w.apply_settings.side_effect = lambda s: self._apply_settings(w, s)
        w.set_weather.side_effect = lambda p: self._set_weather(w, p)
        w.get_blueprint_library.side_effect = lambda: self._library()
        w.spawn_actor.side_effect = functools.partial(self._spawn, w)
        w.tick.side_effect = lambda seconds=10.0: self._tick(w)
        w.get_snapshot.side_effect = lambda: self._snapshot()
        w.get_weather.side_effect = lambda: getattr(self.carla.WeatherParameters, self.weather, None)
        w.get_actors.side_effect = lambda actor_ids=None: [
            r["actor"] for aid, r in sorted(self.alive.items()) if actor_ids is None or aid in actor_ids]
        return w

    def _current(self, w: Any) -> bool:
        if w is not self.world:
            raise RuntimeError(f"stand-in: world of {w.town} used after load_world({self.world.town})")
        return True

    def _load_world(self, map_name: str, reset_settings: bool = True, map_layers: Any = None) -> Any:
        for aid in list(self.alive):
            self.alive.pop(aid)
            self.log.append(("destroyed_by_load", aid))
        if reset_settings:
            self.settings = self.carla.WorldSettings()
        self.world = self._make_world(map_name.rsplit("/", 1)[-1])
        self.log.append(("load_world", self.world.town))
        return self.world

    def _apply_settings(self, w: Any, s: Any) -> int:
        self._current(w)
        self.settings = self._copy_settings(s)
        self.log.append(("apply_settings", bool(s.synchronous_mode), s.fixed_delta_seconds))
        return self.frame

    def _set_weather(self, w: Any, p: Any) -> None:
        self._current(w)
        names = [n for n in dir(self.carla.WeatherParameters) if n[:1].isupper()
                 and getattr(self.carla.WeatherParameters, n) == p]
        self.weather = names[0] if names else "custom"
        self.log.append(("weather", self.weather))

    def _library(self) -> Any:
        lib = self._spec(self.carla.BlueprintLibrary)

        def find(id: str) -> Any:
            bp = self._spec(self.carla.ActorBlueprint)
            bp.id = id
            bp.attrs = {}
            bp.has_attribute.side_effect = lambda name: True
            bp.set_attribute.side_effect = lambda name, value: bp.attrs.__setitem__(name, value)
            return bp

        lib.find.side_effect = find
        return lib

    # -- actors
    def _spawn(self, w: Any, blueprint: Any, transform: Any, attach_to: Any = None,
               attachment_type: Any = None) -> Any:
        self._current(w)
        carla = self.carla
        aid = self._next_id
        self._next_id += 1
        type_id = blueprint.id
        if type_id.startswith("vehicle."):
            actor = self._spec(carla.Vehicle)
            loc, rot = transform.location, transform.rotation
            yaw = math.radians(rot.yaw)
            # our kinematic model in CARLA's frame mirrored to a right-handed one (y -> -y, yaw -> -yaw)
            rear = (loc.x - self.wheelbase / 2 * math.cos(yaw), loc.y - self.wheelbase / 2 * math.sin(yaw))
            veh = Vehicle(VehicleState(rear[0], -rear[1], -yaw),
                          VehicleParams(wheelbase=self.wheelbase, max_wheel_angle_deg=self.max_steer_deg))
            rec = {"actor": actor, "kind": "vehicle", "vehicle": veh, "z": loc.z,
                   "control": carla.VehicleControl()}
            actor.bounding_box = carla.BoundingBox(carla.Location(0.0, 0.0, 0.75), carla.Vector3D(2.45, 1.05, 0.75))
            actor.apply_control.side_effect = lambda c: self._control(aid, c)
            actor.get_transform.side_effect = lambda: self._transform(aid)
            actor.get_velocity.side_effect = lambda: self._velocity(aid)
            actor.get_physics_control.side_effect = lambda: self._physics(aid)
        else:
            actor = self._spec(carla.Sensor)
            kind = ("camera" if type_id.startswith("sensor.camera") else
                    "collision" if type_id.endswith("collision") else
                    "lane_invasion" if type_id.endswith("lane_invasion") else type_id)
            if attach_to is None or attach_to.id not in self.alive:
                raise RuntimeError(f"stand-in: sensor {type_id} attached to no live actor")
            cams = sum(1 for r in self.alive.values() if r["kind"] == "camera")
            rec = {"actor": actor, "kind": kind, "callback": None, "index": cams,
                   "attrs": dict(getattr(blueprint, "attrs", {})), "parent": attach_to.id}
            actor.listen.side_effect = lambda cb: rec.__setitem__("callback", cb)
            actor.stop.side_effect = lambda: rec.__setitem__("callback", None)
            actor.is_listening.side_effect = lambda: rec["callback"] is not None
        actor.id = aid
        actor.type_id = type_id
        actor.is_alive = True
        actor.destroy.side_effect = lambda: self._destroy(aid)
        self.alive[aid] = rec
        self.log.append(("spawn", aid, type_id))
        return actor

    def _destroy(self, aid: int) -> bool:
        rec = self.alive.pop(aid, None)
        if rec is None:
            return False
        rec["actor"].is_alive = False
        self.log.append(("destroy", aid))
        return True

    def _control(self, aid: int, c: Any) -> None:
        if aid not in self.alive:
            raise RuntimeError(f"stand-in: apply_control on destroyed actor {aid}")
        self.alive[aid]["control"] = c
        self.log.append(("control", self.frame, c.steer, c.throttle, c.brake))

    def _pose(self, aid: int) -> tuple[float, float, float, float]:
        rec = self.alive[aid]
        s = rec["vehicle"].s
        cx, cy = s.x + self.wheelbase / 2 * math.cos(s.yaw), s.y + self.wheelbase / 2 * math.sin(s.yaw)
        return cx, -cy, -math.degrees(s.yaw), s.speed

    def _transform(self, aid: int) -> Any:
        carla = self.carla
        x, y, yaw, _ = self._pose(aid)
        return carla.Transform(carla.Location(x=x, y=y, z=self.alive[aid]["z"]), carla.Rotation(yaw=yaw))

    def _velocity(self, aid: int) -> Any:
        _, _, yaw, v = self._pose(aid)
        return self.carla.Vector3D(v * math.cos(math.radians(yaw)), v * math.sin(math.radians(yaw)), 0.0)

    def _physics(self, aid: int) -> Any:
        carla = self.carla
        x, y, yaw, _ = self._pose(aid)
        f, r = math.radians(yaw), math.radians(yaw + 90.0)
        wheels = []
        for along, side, steer in ((0.5, -0.8, self.max_steer_deg), (0.5, 0.8, self.max_steer_deg),
                                   (-0.5, -0.8, 0.0), (-0.5, 0.8, 0.0)):
            px = x + along * self.wheelbase * math.cos(f) + side * math.cos(r)
            py = y + along * self.wheelbase * math.sin(f) + side * math.sin(r)
            wheels.append(carla.WheelPhysicsControl(max_steer_angle=steer,
                                                    position=carla.Vector3D(px * 100.0, py * 100.0, 30.0)))
        return carla.VehiclePhysicsControl(wheels=wheels)

    # -- ticking
    def _tick(self, w: Any) -> int:
        self._current(w)
        if self.on_tick is not None:
            self.on_tick(self.frame + 1)
        self.frame += 1
        dt = float(self.settings.fixed_delta_seconds or DT_DEFAULT)
        for rec in self.alive.values():
            if rec["kind"] == "vehicle":
                c = rec["control"]
                rec["vehicle"].dt = dt
                rec["vehicle"].step(c.steer, c.throttle, c.brake)
        self.log.append(("tick", self.frame, self.weather, bool(self.settings.synchronous_mode),
                         self.settings.fixed_delta_seconds, w.town))
        if self.geometric_sensors:
            self._geometric_events(w)
        for aid, rec in list(self.alive.items()):
            cb = rec.get("callback")
            if cb is None:
                continue
            if rec["kind"] == "camera":
                if self.frame in self.drop:
                    continue
                items = [self._image(rec, self.frame)]
                if self.backlog:
                    items = [self._image(rec, self.frame - 1)] + items + [self._image(rec, self.frame - 2)]
                self._deliver(cb, items)
            elif rec["kind"] == "collision" and self.frame in self.collisions:
                impulse, other = self.collisions[self.frame]
                self._deliver(cb, [self._collision(self.frame, impulse, other)])
            elif rec["kind"] == "lane_invasion" and self.frame in self.invasions:
                self._deliver(cb, [self._invasion(self.frame, self.invasions[self.frame])])
        return self.frame

    def _geometric_events(self, w: Any) -> None:
        """Events a server's sensors would send, from the geometry: a lane invasion when a car's
        centre moves onto another driving lane outside junctions, a collision when two cars' centres
        come within 3 m (impulse 1000 N s per m/s of the moving car's speed)."""
        # (a lane invasion: another lane of the same road; a car off every lane keeps its last lane)
        cmap = self.map(w.town)
        cars = {aid: r for aid, r in self.alive.items() if r["kind"] == "vehicle"}
        for aid, rec in cars.items():
            x, y, _, v = self._pose(aid)
            wp = cmap.get_waypoint(self.carla.Location(x=x, y=y, z=rec["z"]), project_to_road=False)
            lane = None if wp is None or wp.is_junction else (wp.road_id, wp.lane_id)
            last = rec.get("lane")
            if lane is not None and last is not None and lane[0] == last[0] and lane[1] != last[1]:
                self.invasions[self.frame] = self.invasions.get(self.frame, 0) + 1
            if wp is None or lane is not None:
                rec["lane"] = lane if lane is not None else last
            else:
                rec["lane"] = None  # in a junction: a new road follows
            for other, orec in cars.items():
                if other == aid or v < 0.1:
                    continue
                ox, oy, _, _ = self._pose(other)
                if math.hypot(ox - x, oy - y) < 3.0:
                    self.collisions[self.frame] = (1000.0 * v, orec["actor"].type_id)

    def _deliver(self, cb: Callable, items: list) -> None:
        if self.delay_s > 0:
            t = threading.Timer(self.delay_s, lambda: [cb(i) for i in items])
            t.daemon = True
            self.timers.append(t)
            t.start()
        else:
            for i in items:
                cb(i)

    def _image(self, rec: dict, frame: int) -> Any:
        """A camera image (an autospec'd ``carla.Image``; each camera reuses a ring of 8, as the env
        converts every image as soon as it takes it)."""
        ring = rec.setdefault("ring", [])
        if len(ring) < 8:
            ring.append(self._spec(self.carla.Image))
        img = ring[rec.setdefault("next", 0) % len(ring)]
        rec["next"] += 1
        w = int(rec["attrs"].get("image_size_x", self.image_size[0]))
        h = int(rec["attrs"].get("image_size_y", self.image_size[1]))
        if self.image_size_override is not None:
            w, h = self.image_size_override
        img.frame, img.width, img.height = frame, w, h
        img.raw_data = bytes((frame % 256, frame // 256 % 256, rec["index"], 255)) * (w * h)  # B, G, R, A
        return img

    def _collision(self, frame: int, impulse: float, other: str) -> Any:
        ev = self._spec(self.carla.CollisionEvent)
        o = self._spec(self.carla.Actor)
        o.type_id = other
        ev.frame, ev.other_actor, ev.normal_impulse = frame, o, self.carla.Vector3D(impulse, 0.0, 0.0)
        return ev

    def _invasion(self, frame: int, n: int) -> Any:
        ev = self._spec(self.carla.LaneInvasionEvent)
        ev.frame, ev.crossed_lane_markings = frame, [self._spec(self.carla.LaneMarking) for _ in range(n)]
        return ev

    def _snapshot(self) -> Any:
        """The world snapshot of the current frame (one autospec'd ``WorldSnapshot``, updated)."""
        if not hasattr(self, "_snap"):
            self._snap = self._spec(self.carla.WorldSnapshot)
            self._actor_snaps: dict[int, Any] = {}
            self._snap.find.side_effect = self._find
        self._snap.frame = self.frame
        self._states = {aid: (self._transform(aid), self._velocity(aid)) for aid, r in self.alive.items()
                        if r["kind"] == "vehicle"}
        return self._snap

    def _find(self, actor_id: int) -> Any:
        if actor_id not in self._states:
            return None
        if actor_id not in self._actor_snaps:
            a = self._spec(self.carla.ActorSnapshot)
            a.get_transform.side_effect = lambda: self._states[actor_id][0]
            a.get_velocity.side_effect = lambda: self._states[actor_id][1]
            self._actor_snaps[actor_id] = a
        return self._actor_snaps[actor_id]

    # -- what the tests read
    def ticks(self) -> list[tuple]:
        return [e for e in self.log if e[0] == "tick"]

    def controls(self) -> list[tuple]:
        return [e for e in self.log if e[0] == "control"]

    def settings_now(self) -> tuple[bool, float | None]:
        return bool(self.settings.synchronous_mode), self.settings.fixed_delta_seconds

    def episodes(self) -> list[dict]:
        """The log cut into episodes, from a car's spawn to its destruction: ``car`` (its id), ``ticks`` and
        ``controls`` in between. Raises AssertionError if a car was spawned while another was alive or
        was never destroyed."""
        out, cur = [], None
        for e in self.log:
            if e[0] == "spawn" and e[2].startswith("vehicle."):
                if cur is not None:
                    raise AssertionError("a car was spawned while another episode's car was alive")
                cur = {"car": e[1], "ticks": [], "controls": []}
            elif e[0] == "tick" and cur is not None:
                cur["ticks"].append(e)
            elif e[0] == "control" and cur is not None:
                cur["controls"].append(e)
            elif e[0] in ("destroy", "destroyed_by_load") and cur is not None and e[1] == cur["car"]:
                out.append(cur)
                cur = None
        if cur is not None:
            raise AssertionError("an episode's car was never destroyed")
        return out

    def leftovers(self) -> list[str]:
        """What a client left wrong: live actors, settings not restored, calls that bind to no stub
        signature, non-finite or out-of-range controls; [] when all is well."""
        out = [f"actor left: {r['actor'].type_id} ({aid})" for aid, r in sorted(self.alive.items())]
        if self.settings_now() != (False, None):
            out.append(f"settings not restored: synchronous, fixed_delta = {self.settings_now()}")
        out += self.check_calls()
        out += [f"control {c[2:]} at frame {c[1]}" for c in self.controls()
                if not all(math.isfinite(v) for v in c[2:]) or abs(c[2]) > 1.0]
        return out

    @staticmethod
    def decode_frame(image: np.ndarray) -> int:
        """The frame id a stand-in camera image encodes (after cicfw's crop, resize and BGRA -> RGB)."""
        px = image[image.shape[0] // 2, image.shape[1] // 2]
        return int(px[2]) + 256 * int(px[1])
