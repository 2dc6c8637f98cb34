"""The simulator backend interface, and the embedded simulator's backend (``SIM_BACKENDS`` "embedded").

A backend is built from its config's kwargs (``conf/sim/<name>.yaml``: ``name:`` + kwargs) and gives
``towns()``, ``weathers()``, ``single_turn_routes(town)`` and ``make_env(town, route, weather, seed,
cameras, renderer) -> env`` where env has ``reset() -> obs``, ``step(steer, target_speed_kmh=...) ->
(obs, done, info)`` and ``expert_action()``, as ``cicfw.sim.env.DrivingEnv``. The data collector
(``cicfw.collect``) needs a little more: ``random_route``, ``make_env(..., expert=, time_offset=,
endless=)`` and optionally ``resolve_town``; its package docstring lists the whole interface.
``lockstep``: True when many episodes may run side by side (embedded); False for a backend whose server
runs one episode at a time (CARLA, ``cicfw.carla_client.backend``, which registers "carla" itself): the
runner then drives episodes one after another and ``runner.workers`` is a list of server ports.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from cicfw.core.config_checks import is_number
from cicfw.core.errors import CicfwError, ConfigError
from cicfw.registry import SIM_BACKENDS
from cicfw.sim.env import DrivingEnv
from cicfw.sim.expert import ExpertParams
from cicfw.sim.render.weather import get_weather, weather_family as presets_of
from cicfw.sim.roadgraph import COMMAND_DISTANCE, Route, road_graph, single_turn_routes
from cicfw.sim.town import TownError, load_town, town_names


def positive_distances(**distances: Any) -> tuple[float, ...]:
    """A backend's distances in metres (``success_radius=2.0`` ...) as floats, in the order given; one that is
    not a finite number > 0 is a ``ConfigError`` naming ``sim.<name>``: a radius of -1 failed every episode;
    so is a ``success_radius`` of ``route_after`` or more, which let every episode succeed at its start."""
    for key, value in distances.items():
        if not (is_number(value) and value > 0):
            raise ConfigError(f"sim.{key}", value, "a distance in metres > 0")
    radius, after = distances.get("success_radius"), distances.get("route_after")
    if radius is not None and after is not None and radius >= after:  # success before the turn is driven
        raise ConfigError("sim.success_radius", radius, f"a distance in metres < sim.route_after ({after:g}): the "
                          f"goal lies route_after past the junction, so a radius this large counts the car as arrived "
                          f"before it has turned")
    return tuple(float(v) for v in distances.values())


@SIM_BACKENDS.register("embedded")
class EmbeddedBackend:
    """The simulator shipped with cicfw: towns from ``conf/town``, weathers from ``cicfw.sim.render``.

    ``weather_family`` picks how a weather name is rendered: ``carla`` (derived from CARLA's parameters
    for the name) or ``harsh`` (the hand-set presets of every result driven before the families)."""

    #: episodes of a run share nothing, so the runner steps them all together (one policy call a step)
    lockstep = True

    def __init__(self, command_distance: float = COMMAND_DISTANCE, success_radius: float = 2.0,
                 max_deviation: float = 10.0, route_before: float = 30.0, route_after: float = 25.0,
                 weather_family: str = "carla") -> None:
        try:
            presets_of(weather_family)
        except ValueError as err:
            raise CicfwError(f"sim.weather_family: {err}", key="sim.weather_family", value=weather_family) from None
        self.weather_family = weather_family
        self.command_distance, self.success_radius, self.max_deviation, self.route_before, self.route_after = \
            positive_distances(command_distance=command_distance, success_radius=success_radius,
                               max_deviation=max_deviation, route_before=route_before, route_after=route_after)

    def towns(self) -> list[str]:
        return town_names()

    def weathers(self) -> list[str]:
        return list(presets_of(self.weather_family))

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
        cd = self.command_distance if command_distance is None else float(command_distance)
        return road_graph(load_town(town), cd).random_route(rng, min_length=min_length, name=name, counts={})

    def make_env(self, town: str, route: Route, weather: str, seed: int = 0, cameras: tuple = ("centre",),
                 renderer: bool | Any = True, expert: dict | None = None, time_offset: float = 0.0,
                 endless: bool = False):
        """``expert``: ExpertParams overrides; ``time_offset``: shifts the renderer's clock (rain phase);
        ``endless``: the episode never ends by itself (no success, timeout or lost), for collection."""
        stop = (dict(timeout=1e9, max_deviation=1e9, success_radius=-1.0) if endless else
                dict(success_radius=self.success_radius, max_deviation=self.max_deviation))
        preset = get_weather(weather, self.weather_family)  # the name in this backend's family
        return DrivingEnv(load_town(town), route, weather=preset, seed=seed, cameras=cameras,
                          renderer=renderer, expert=ExpertParams(**(expert or {})), time_offset=time_offset,
                          **stop)

