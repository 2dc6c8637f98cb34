"""The closed-loop suites: every junction manoeuvre of each town, under each weather.

The start/goal pairs come from the simulator backend's ``single_turn_routes(town)`` (one route per
possible way through every junction, each needing exactly one decision; stable for a given town
file). A suite is named by the manoeuvres it keeps (``SUITES``): the paper's ``single_turn`` task
forces exactly one turn per episode (left and right turns only, as in the paper), ``junctions``
also drives straight through each crossing. Pair numbers always index the town's full route list,
so an episode's key is the same in both suites. An ``Episode`` is plain data (town, weather, pair index) so worker processes rebuild the route
themselves. Towns and weathers are grouped as in the paper's table: training vs new.
"""
from __future__ import annotations

import functools
import logging
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

from cicfw.core.config_checks import whole_number
from cicfw.core.errors import CicfwError, ConfigError
from cicfw.registry import SIM_BACKENDS
from cicfw.sim.render.weather import DEFAULT_FAMILY, NEW_WEATHERS, TRAINING_WEATHERS
from cicfw.sim.roadgraph import COMMAND_NAMES

log = logging.getLogger(__name__)

#: the paper's four weathers: two seen in training, two new
PAPER_WEATHERS = (*TRAINING_WEATHERS, *NEW_WEATHERS)
#: the town the default data is collected in: the table's "Training town" columns unless told otherwise
TRAINING_TOWNS = ("town_a",)
#: the paper's table columns, in its order: (town set, weather set)
CELLS = (("training", "training"), ("training", "new"), ("new", "training"), ("new", "new"))
#: the named suites: the manoeuvres each one drives (conf/suite/<name>.yaml selects one)
SUITES = {
    "single_turn": ("left", "right"),  # the paper's test: exactly one turn per episode
    "junctions": ("left", "right", "straight"),  # every way through every junction
}
#: the evaluate override that picks how the embedded simulator renders a weather name (conf/sim/embedded.yaml)
WEATHER_FAMILY_KEY = "sim.weather_family"


@dataclass(frozen=True)
class Episode:
    """One episode of the suite: the ``pair``-th single-turn route of ``town`` under ``weather``."""

    index: int  # position in the run (0..N-1)
    town: str  # town name (or path) as the backend takes it
    weather: str
    pair: int  # index into the town's single-turn routes
    route: str  # the route's name, e.g. town_a/c1/c1-n1>s1-c1/straight
    command: str  # the turn: left | right | straight
    town_set: str  # "training" | "new"
    weather_set: str  # "training" | "new"

    @property
    def key(self) -> str:
        """A stable id independent of which subset was run: ``town/weather/pair``."""
        return f"{town_label(self.town)}/{self.weather}/{self.pair:03d}"

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def town_label(town: str) -> str:
    """The short name of a town given by name or by a path to its YAML file."""
    s = str(town)
    return Path(s).stem if s.endswith((".yaml", ".yml")) else s


def make_backend(spec: Mapping[str, Any] | None):
    """The simulator backend from its config node (``name:`` + kwargs; default: embedded)."""
    kwargs = dict(spec or {"name": "embedded"})
    name = kwargs.pop("name", "embedded")
    return SIM_BACKENDS.get(str(name))(**kwargs)


@functools.lru_cache(maxsize=32)
def suite_routes(backend: Any, town: str) -> tuple:
    """The backend's single-turn routes of ``town`` (cached per backend object)."""
    return tuple(backend.single_turn_routes(town))


def check_names(kind: str, given: Iterable[str], known: Sequence[str], path_ok: bool = False) -> list[str]:
    """``given`` as a list, or one error naming the first unknown entry and listing the known ones."""
    out = [given] if isinstance(given, str) else [str(g) for g in given]  # one name, not its letters
    if not out:
        raise CicfwError(f"the suite needs at least one {kind}; known {kind}s: {', '.join(known)}")
    for g in out:
        if g in known or (path_ok and g.endswith((".yaml", ".yml")) and Path(g).expanduser().is_file()):
            continue
        if path_ok and (g.endswith((".yaml", ".yml")) or "/" in g or "\\" in g) and not Path(g).expanduser().exists():
            raise CicfwError(f"{kind} file {g!r}: no such file (a {kind} is a name, {', '.join(known)}, "
                             f"or the path of an existing {kind} .yaml file)", value=g)
        extra = " (or a path to a town .yaml file)" if path_ok else ""
        raise CicfwError(f"unknown {kind} {g!r}; known {kind}s: {', '.join(known)}{extra}", value=g)
    return out


def training_set(kind: str, given: Any, accepted: Sequence[str], driven: Sequence[str] = ()) -> list[str]:
    """``suite.training_<kind>`` as a list, each entry among ``accepted``: the suite's towns (those it drives
    and the simulator's others) or weathers (those it drives and the paper's four, which a subset such as
    ``suite.weathers=[MidRainyNoon]`` leaves undriven). Any other name is a ``ConfigError`` naming it: an
    unknown town or an undriven weather would silently move the driven ones to the "new" columns. The error
    lists ``driven`` (the suite's own, as configured), not every name accepted."""
    out = [str(given)] if isinstance(given, str) else [str(g) for g in (given or ())]
    names = list(dict.fromkeys(accepted))
    shown = ", ".join(dict.fromkeys(driven or names))
    for g in out:
        if g not in names:
            raise ConfigError(f"suite.training_{kind}", g, f"among the suite's {kind} ({shown})",
                              f"suite.training_{kind}: {g!r} is not among the suite's {kind} ({shown}); "
                              f"the table's training columns are the driven {kind} named there, the others new")
    return out


def suite_manoeuvres(name: str) -> tuple[str, ...]:
    """The manoeuvres of the suite called ``name``, or one error listing the known suites."""
    if name not in SUITES:
        raise CicfwError(f"unknown suite {name!r}; known suites: "
                         + ", ".join(f"{k} ({'/'.join(v)})" for k, v in SUITES.items()))
    return SUITES[name]


def build_suite(backend: Any, towns: Sequence[str], weathers: Sequence[str],
                training_towns: Sequence[str] | None = None, training_weathers: Sequence[str] = TRAINING_WEATHERS,
                pairs: Sequence[int] | None = None, limit: int | None = None,
                name: str = "junctions") -> list[Episode]:
    """Every (town, weather, pair) of the suite ``name`` (``SUITES``), ordered by town, weather, pair.

    Only the pairs whose manoeuvre belongs to the suite are kept (``single_turn``: left and right);
    ``pairs`` keeps only those pair indices (per town, numbered over all the town's routes); ``limit``
    keeps the first ``limit`` kept pairs of each town. ``training_towns`` None: ``TRAINING_TOWNS`` (as
    conf/suite/ sets it), where the simulator has it. Unknown town, weather or suite names raise one
    error listing the known ones.
    """
    manoeuvres = suite_manoeuvres(str(name))
    if limit is not None:
        limit = whole_number("suite.limit", limit, "an integer >= 1 (or null for every pair)")
        if limit < 1:
            raise CicfwError(f"suite.limit must be >= 1 (or null for every pair), got {limit}")
    if pairs is not None:
        pairs = _pair_list(pairs)
    towns = check_names("town", towns, backend.towns(), path_ok=True)
    weathers = check_names("weather", weathers, backend.weathers())
    for key, names in (("suite.towns", towns), ("suite.weathers", weathers)):
        if len(set(names)) < len(names):  # a repeat would drive its episodes twice and count them twice
            raise ConfigError(key, list(names), "a list of distinct names (each is driven once)")
    labels = [town_label(t) for t in towns]
    clash = next((t for i, t in enumerate(towns) if labels[i] in labels[:i]), None)
    if clash is not None:  # episodes are keyed <town label>/<weather>/<pair>: two towns would share keys
        first = towns[labels.index(town_label(clash))]
        raise ConfigError("suite.towns", clash, "towns with distinct names",
                          f"suite.towns: {clash!r} and {first!r} are both named {town_label(clash)!r}, so their "
                          f"episodes would share keys (and trajectories, map, report rows); rename one town file")
    accepted = [*towns, *map(town_label, towns), *backend.towns()]
    if training_towns is None:  # as conf/suite/ says, so a Python caller's table labels town_a as the app's does
        training_towns = [t for t in TRAINING_TOWNS if t in accepted]
    training_towns = training_set("towns", training_towns, accepted, [town_label(t) for t in towns])
    training_weathers = training_set("weathers", training_weathers, [*weathers, *PAPER_WEATHERS], weathers)
    episodes: list[Episode] = []
    for town in towns:
        routes = suite_routes(backend, town)
        chosen = range(len(routes)) if pairs is None else pairs
        bad = [p for p in chosen if not 0 <= p < len(routes)]
        if bad:
            raise CicfwError(f"suite.pairs: pair {bad[0]} does not exist in town {town!r}, which has "
                             f"{len(routes)} pairs (0..{len(routes) - 1})", key="suite.pairs", value=bad[0])
        left_out = [p for p in chosen if _turn_name(routes[p]) not in manoeuvres]
        if left_out and pairs is not None:  # asked for by number: say which ones the suite does not drive
            log.warning("suite.pairs: %s of town %r %s not a %s manoeuvre, which suite=%s does not drive: left out",
                        ", ".join(f"pair {p} ({_turn_name(routes[p])})" for p in left_out), town,
                        "is" if len(left_out) == 1 else "are", "/".join(manoeuvres), name)
        chosen = [p for p in chosen if p not in left_out]
        if not chosen:
            raise CicfwError(f"suite {name!r} ({'/'.join(manoeuvres)}) keeps none of the chosen pairs of "
                             f"town {town!r}; pick other suite.pairs or suite=junctions")
        if limit is not None:
            chosen = list(chosen)[:limit]
        town_set = "training" if town in training_towns or town_label(town) in training_towns else "new"
        for weather in weathers:
            for p in chosen:
                r = routes[p]
                episodes.append(Episode(
                    index=len(episodes), town=town, weather=weather, pair=p, route=r.name,
                    command=_turn_name(r), town_set=town_set,
                    weather_set="training" if weather in training_weathers else "new"))
    return episodes


def _pair_list(pairs: Any) -> list[int]:
    """``suite.pairs`` as a list of pair indices, else one line naming it (not int()'s own message)."""
    accepted = "a list of pair indices such as [0, 2] (or null for every pair)"
    if isinstance(pairs, str) or not isinstance(pairs, Sequence):
        raise CicfwError(f"suite.pairs must be {accepted}, got {pairs!r}")
    out = [whole_number("suite.pairs", p, accepted) for p in pairs]
    repeated = next((p for i, p in enumerate(out) if p in out[:i]), None)
    if repeated is not None:  # as with towns and weathers: it would be driven twice and counted twice
        raise ConfigError("suite.pairs", repeated, "a list of distinct pair indices (each is driven once)",
                          f"suite.pairs lists pair {repeated} twice; each pair is driven once, so give it once")
    return out


def _turn_name(route: Any) -> str:
    code = (route.meta or {}).get("command")
    if code is None and route.turns:
        code = route.turns[0][1]
    return COMMAND_NAMES.get(int(code), "?") if code is not None else "?"


def _override_value(overrides: Sequence[str], key: str) -> str | None:
    """The value the last of ``overrides`` (``key=value`` strings) gives ``key``, or None."""
    values = [o.split("=", 1)[1] for o in overrides if "=" in o and o.split("=", 1)[0].lstrip("+~") == key]
    return values[-1] if values else None


def named_weather_family(overrides: Sequence[str]) -> str | None:
    """The weather family a list of evaluate overrides names, or None when it names none."""
    return _override_value(overrides, WEATHER_FAMILY_KEY)


def with_weather_family(overrides: Sequence[str], family: str | None = None, default: str | None = None) -> list[str]:
    """``overrides`` naming the embedded simulator's weather family explicitly: ``family`` when given,
    else the one they name, else ``default`` (the simulator's own default when None). Overrides that
    pick another simulator come back as they are: its weathers are its own."""
    out = [str(o) for o in overrides]
    if _override_value(out, "sim") not in (None, "embedded"):
        return out
    named = named_weather_family(out)
    wanted = family if family is not None else named if named is not None else default or DEFAULT_FAMILY
    return out if named == wanted else [*out, f"{WEATHER_FAMILY_KEY}={wanted}"]
