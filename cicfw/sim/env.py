"""A driving episode on a route: ``DrivingEnv(town, route, weather, seed, cameras)``.

``reset() -> obs``; ``step(steer, target_speed_kmh=... | throttle=..., brake=..., render=True) -> (obs, done, info)``;
``render() -> images`` of the current state (after ``step(..., render=False)``: a caller that decides
whether it needs the frame, as the benchmark's runner does, renders only the frames it serves).
obs: ``images`` (camera -> (88, 200, 3) uint8, empty without a renderer), ``speed_kmh``, ``command``
(CIL code at the car's place on the route), ``pose`` (x, y, yaw of the rear axle), ``t`` (s),
``target_speed_kmh`` (the expert's planned speed here, for steering-only policies).
info: ``distance_to_goal``, ``route_deviation``, ``progress`` (0-1), ``opposite_lane`` and ``off_road``
(fractions of the car's width, CIL targets 14/15), ``in_junction``, ``success``, ``reason``
("success" | "timeout" | "lost" | None).
``seed`` selects the renderer (textures are baked per renderer, seconds, and cached), ``time_offset``
shifts the time the renderer sees (animated rain), so episodes can differ while sharing a renderer.
An episode ends when the rear axle is within ``success_radius`` (2 m) of the goal (success), at
the route's timeout (length at 10 km/h + 10 s), or when the car is ``max_deviation`` m off the route
(it can no longer reach the goal; stopping early only saves time).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from cicfw.sim.episode import step_info
from cicfw.sim.expert import Expert, ExpertParams, Noiser
from cicfw.sim.render import Renderer
from cicfw.sim.roadgraph import Route
from cicfw.sim.town import Town, load_town
from cicfw.sim.townmap import town_map
from cicfw.sim.vehicle import DT, SpeedController, Vehicle, VehicleParams, VehicleState

_RENDERERS: dict[tuple, Any] = {}
MAX_RENDERERS = 8  # a renderer bakes its textures once (seconds); keep the last few


def get_renderer(town: Town, weather: str, seed: int = 0, cameras: tuple = ("centre",)):
    """A cached ``cicfw.sim.render.Renderer`` (a world without images never builds one).

    Building one bakes textures (seconds), so share them: vary ``DrivingEnv(time_offset=...)`` rather
    than the renderer seed from episode to episode."""
    key = (id(town), weather, seed, tuple(cameras))
    if key in _RENDERERS:
        _RENDERERS[key] = _RENDERERS.pop(key)  # most recently used last
    else:
        while len(_RENDERERS) >= MAX_RENDERERS:
            _RENDERERS.pop(next(iter(_RENDERERS)))
        _RENDERERS[key] = (town, Renderer(town, weather, seed=seed, cameras=tuple(cameras)))
    return _RENDERERS[key][1]


class DrivingEnv:
    """One car driving one route in a town; rendering optional."""

    def __init__(self, town: Town | str, route: Route | None = None, weather: str = "ClearNoon",
                 seed: int = 0, cameras: tuple = ("centre",), renderer: bool | Any = True,
                 vehicle: VehicleParams | None = None, expert: ExpertParams | None = None,
                 success_radius: float = 2.0, max_deviation: float = 10.0, timeout: float | None = None,
                 start_speed_kmh: float = 0.0, time_offset: float = 0.0) -> None:
        self.town = load_town(town) if isinstance(town, str) else town
        self.route = route
        self.weather = weather
        self.seed = seed
        self.cameras = tuple(cameras)
        self.vehicle_params = vehicle or VehicleParams()
        self.expert_params = expert or ExpertParams()
        self.success_radius = success_radius
        self.max_deviation = max_deviation
        self._timeout = timeout
        self.start_speed = start_speed_kmh / 3.6
        self.time_offset = time_offset  # added to the time the renderer sees (rain phase per episode)
        self.map = town_map(self.town)
        if renderer is True:
            self.renderer = get_renderer(self.town, weather, seed, self.cameras)
        elif renderer is False or renderer is None:
            self.renderer = None
        else:
            self.renderer = renderer  # a Renderer instance shared by the caller
        self.vehicle: Vehicle | None = None
        self.speed_ctl = SpeedController(params=self.vehicle_params)
        self.expert: Expert | None = None
        self.t = 0.0
        self.steps = 0
        self.done = False

    @property
    def timeout(self) -> float:
        return self._timeout if self._timeout is not None else self.route.timeout()

    def reset(self, route: Route | None = None) -> dict:
        if route is not None:
            self.route = route
        if self.route is None:
            raise ValueError("DrivingEnv.reset: no route; pass route= (see cicfw.sim.roadgraph)")
        x, y, yaw = self.route.start_pose
        self.vehicle = Vehicle(VehicleState(x, y, yaw, speed=self.start_speed), self.vehicle_params, DT)
        self.expert = Expert(self.route, self.expert_params, self.vehicle_params)
        self.speed_ctl.reset()
        self.t, self.steps, self.done = 0.0, 0, False
        return self._obs()

    def expert_action(self) -> tuple[float, float]:
        """What the expert would do now: (steer in [-1, 1], target speed km/h)."""
        steer, v = self.expert.act(self.vehicle.s)
        return steer, v * 3.6

    def step(self, steer: float, target_speed_kmh: float | None = None, throttle: float | None = None,
             brake: float | None = None, render: bool = True) -> tuple[dict, bool, dict]:
        """Advance 0.1 s. ``render=False``: the new observation's ``images`` are left empty ({}) and
        ``render()`` draws them on demand (the same frame: the renderer is a function of the pose and the
        time), so a frame nobody will see, such as the one after the step that ends an episode, is not drawn."""
        if self.vehicle is None:
            raise RuntimeError("DrivingEnv.step before reset()")
        if self.done:
            raise RuntimeError("DrivingEnv.step after the episode ended; call reset()")
        s = self.vehicle.s
        if target_speed_kmh is not None:
            throttle, brake = self.speed_ctl(s.speed, target_speed_kmh / 3.6)
        elif throttle is None:
            raise ValueError("DrivingEnv.step needs target_speed_kmh= or throttle= (and brake=)")
        self.vehicle.step(steer, throttle, brake or 0.0)
        self.t += DT
        self.steps += 1
        s = self.vehicle.s
        i = self.expert.locate(s.x, s.y)  # once per step; _obs and info reuse it
        obs = self._obs(i, render=render)
        info = self.info(i)
        self.done = info["reason"] is not None
        return obs, self.done, info

    def render(self) -> dict:
        """The cameras' images of the current state ({} without a renderer): what ``step`` puts in the
        observation when it renders."""
        if self.renderer is None or self.vehicle is None:
            return {}
        s = self.vehicle.s
        return self.renderer.render(s.x, s.y, s.yaw, self.t + self.time_offset)

    def info(self, i: int | None = None) -> dict:
        s = self.vehicle.s
        if i is None:
            i = self.expert.locate(s.x, s.y)
        in_j, opp, off, _ = self.map.query(*self.vehicle.centre(), s.yaw, self.vehicle_params.width / 2)
        return step_info(self.route, s.x, s.y, i, self.t, self.success_radius, self.timeout, self.max_deviation,
                         (in_j, opp, off))

    def _obs(self, i: int | None = None, render: bool = True) -> dict:
        s = self.vehicle.s
        if i is None:
            i = self.expert.locate(s.x, s.y)
        images = self.render() if render else {}
        return {"images": images, "speed_kmh": s.speed * 3.6, "command": int(self.route.commands[i]),
                "pose": (s.x, s.y, s.yaw), "t": self.t,
                "target_speed_kmh": float(self.expert.profile[min(i + 4, len(self.expert.profile) - 1)]) * 3.6}


def run_expert(env: DrivingEnv, noise_rng: np.random.Generator | None = None) -> dict:
    """Drive ``env``'s route with the expert (and CIL noise when ``noise_rng`` is given) until done;
    the final info plus ``steps``, ``noisy_steps`` and the worst ``max_route_deviation``,
    ``max_opposite_lane``, ``max_off_road`` of the episode."""
    env.reset()
    noiser = Noiser(noise_rng, enabled=True) if noise_rng is not None else None
    info: dict = {}
    noisy, worst = 0, {"route_deviation": 0.0, "opposite_lane": 0.0, "off_road": 0.0}
    while not env.done:
        steer, v = env.expert_action()
        applied = steer
        if noiser is not None:
            applied, flag = noiser.step(steer, env.vehicle.s.speed_kmh)
            noisy += flag
        _, _, info = env.step(applied, target_speed_kmh=v)
        for k in worst:
            worst[k] = max(worst[k], info[k])
    info.update(steps=env.steps, noisy_steps=noisy, **{f"max_{k}": v for k, v in worst.items()})
    return info
