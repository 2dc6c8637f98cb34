"""The collect config: ``CollectConfig``, the one place its keys, types and defaults live (conf/collect.yaml
and ``data.collect`` take them from it through the apps' config schemas, cicfw/collect/schema.py and
cicfw/train/schema.py); its validation (one clear error per bad key), its hash, the simulator backend it
names, and what it collects: every episode's id, town, weather and seed, its steps, and its size on disk."""
from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Optional

import numpy as np
from omegaconf import OmegaConf

from cicfw.collect.errors import CollectConfigError, CollectError
from cicfw.core.config_checks import SchemaError, checked, is_number
from cicfw.data.cil_hdf5 import IMAGE_SHAPE, N_TARGETS, SAMPLES_PER_FILE
from cicfw.registry import SIM_BACKENDS, UnknownNameError
from cicfw.sim.expert import ExpertParams
from cicfw.sim.roadgraph import COMMAND_DISTANCE
from cicfw.sim.render.weather import DEFAULT_FAMILY, family_data_tag

CAMERA_IDS = {"centre": (0, 0.0), "left": (1, -30.0), "right": (2, 30.0)}  # name -> (targets[26], [27])


@dataclass
class NoiseConfig:
    """CIL's steering-noise injection (the label stays the expert's steer)."""

    episode_fraction: float = 0.75  # share of episodes with noise on
    frequency: int = 15  # spikes start with probability frequency/61 each second
    intensity: float = 10.0  # +-2 per episode; the spike grows by 0.03*intensity per second


@dataclass
class CollectConfig:
    """What a collection records and how. ``towns``, ``weathers`` and ``cameras`` are lists of names (one
    name alone counts as a list of one); ``expert`` is ``cicfw.sim.expert.ExpertParams``."""

    __cicfw_what__ = "the collection (CollectConfig)"  # config_checks.WHAT: how messages name it

    towns: Any = field(default_factory=lambda: ["town_a"])  # conf/town/<name>.yaml, or paths to town files
    weathers: Any = field(default_factory=lambda: ["ClearNoon", "ClearSunset"])  # cicfw.sim.render.WEATHERS
    episodes: int = 36  # in total, spread round-robin over towns x weathers
    seconds: float = 40.0  # per episode (10 steps a second)
    seed: int = 0  # every episode's route, noise and rain derive from it
    cameras: Any = field(default_factory=lambda: ["centre", "left", "right"])  # ids 0, 1, 2; yaw 0, -30, +30
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    expert: ExpertParams = field(default_factory=ExpertParams)  # the expert driver's values
    command_distance: float = 12.0  # metres before a junction where its turn command starts
    workers: int = 2  # processes; 0 or 1 = in this process
    lock_wait: Optional[float] = None  # seconds to wait for another process collecting into the folder
    #                                    (0: refuse at once, naming it; None: wait as long as it takes)
    sim: Any = field(default_factory=lambda: {"name": "embedded"})  # the backend: conf/sim/<name>.yaml


DEFAULTS: dict[str, Any] = asdict(CollectConfig())
#: the values the numbers of a collection accept (a type cannot say them): key -> (test, what is accepted)
VALUES = {
    "episodes": (lambda v: v >= 1, "an integer >= 1"),
    "seconds": (lambda v: math.isfinite(v) and round(v * 10) >= 1, "> 0 (at least 0.1: one step at 10 Hz)"),
    "seed": (lambda v: v >= 0, "an integer >= 0 (every episode's route, noise and rain derive from it)"),
    "workers": (lambda v: v >= 0, "an integer >= 0 (0 or 1: in this process)"),
    "command_distance": (lambda v: is_number(v) and v > 0, "metres > 0"),
    "noise.episode_fraction": (lambda v: is_number(v) and 0.0 <= v <= 1.0, "in [0, 1]"),
    "noise.frequency": (lambda v: v >= 0, "an integer >= 0"),
    "noise.intensity": (lambda v: is_number(v) and v >= 0, ">= 0"),
}
# keys that do not change the data (left out of the config hash, so a rerun may change them)
_NOT_DATA = ("workers", "lock_wait", "sim", "_hash")


def close_backend(backend: Any) -> None:
    """Release a backend's simulator (a CARLA server's world) if it has anything to release."""
    if backend is not None and hasattr(backend, "close"):
        backend.close()


def plain_config(cfg: Any) -> dict:
    """The collect config as a plain dict without the app's keys (out_dir, hydra); verify=true is refused."""
    if cfg is None:
        return {}
    if not isinstance(cfg, dict):
        cfg = OmegaConf.to_container(cfg, resolve=True)
    if cfg.get("verify"):  # the app's switch (cicfw collect --verify): it never reaches a collection
        raise CollectConfigError("collect: verify=true checks a collected folder and is the collect app's switch "
                                 "(python -m cicfw.collect out_dir=... verify=true); a collection cannot take it")
    return {k: v for k, v in cfg.items() if k not in ("out_dir", "hydra", "verify")}


def sim_node(cfg: dict) -> dict:
    """The config's ``sim`` node (backend name + kwargs), ``embedded`` unless it names another."""
    sim = cfg.get("sim", DEFAULTS["sim"])
    if not isinstance(sim, dict) or not isinstance(sim.get("name", "embedded"), str):
        raise CollectConfigError(f"collect.sim must be a backend config with a name (sim=embedded | sim=carla), "
                                 f"got {sim!r}")
    return {"name": "embedded", **sim}


def make_backend(sim: dict) -> Any:
    """The backend of a ``sim`` config node (``name`` + kwargs); one clear error when it cannot be built."""
    kwargs = dict(sim)
    name = str(kwargs.pop("name", "embedded"))
    try:
        cls = SIM_BACKENDS.get(name)
    except UnknownNameError as err:
        raise CollectConfigError(f"collect: {err}") from None
    try:
        return cls(**kwargs)
    except ImportError as err:  # an optional simulator package that is not installed
        raise CollectError(str(err)) from None
    except TypeError as err:
        raise CollectConfigError(f"sim={name}: {err}") from None


def _is_path(town: str) -> bool:
    return town.endswith((".yaml", ".yml")) or "/" in town or "\\" in town


def town_key(town: str) -> str:
    """The name used in file and episode names: a town's name, or a town file's stem."""
    return Path(town).stem if _is_path(town) else town


def resolve_config(cfg: Any, backend: Any = None) -> dict:
    """The collect config as a plain dict over DEFAULTS, validated (one clear error per bad key).

    Towns given by path come back as absolute paths. ``backend``: the sim backend, if already built
    (otherwise one is built for the check and closed)."""
    cfg = plain_config(cfg)
    try:  # unknown keys and types (the schema); the values each key accepts are checked below
        typed = checked(CollectConfig, cfg, "collect")
    except SchemaError as err:
        refused = CollectConfigError(str(err))
        refused.key, refused.kind = err.key, err.kind
        raise refused from None

    out = OmegaConf.to_container(typed, resolve=True)
    for k in ("towns", "weathers", "cameras"):
        if isinstance(out[k], str):
            out[k] = [out[k]]
        if not isinstance(out[k], (list, tuple)) or not all(isinstance(x, str) for x in out[k]):
            raise CollectConfigError(f"collect.{k} must be a list of names, got {out[k]!r}")
        out[k] = list(out[k])
    for key, (ok, accepted) in VALUES.items():  # the schema checked the types: numbers, integers where said
        value = OmegaConf.select(typed, key)
        if not ok(value):
            raise CollectConfigError(f"collect.{key} must be {accepted}, got {value!r}", key=f"collect.{key}",
                                     value=value)
    check_lock_wait(out["lock_wait"])
    if not out["cameras"]:
        raise CollectConfigError(f"collect.cameras is empty; known: {', '.join(CAMERA_IDS)}")
    for c in out["cameras"]:
        if c not in CAMERA_IDS:
            raise CollectConfigError(f"collect.cameras: unknown camera {c!r}; known: {', '.join(CAMERA_IDS)}",
                                     key="collect.cameras", value=c)
    if len(set(out["cameras"])) != len(out["cameras"]):
        raise CollectConfigError(f"collect.cameras lists a camera twice: {out['cameras']}")
    accepted = DEFAULTS["expert"]
    try:  # values the expert cannot drive with (a negative speed, a look-ahead of 0)
        ExpertParams(**out["expert"])
    except ValueError as err:
        raise CollectConfigError(f"collect.{err}") from None
    # only the values that differ from the defaults are kept: the defaults hash as {}
    out["expert"] = {k: v for k, v in out["expert"].items() if v != accepted[k]}
    out["sim"] = sim_node(out)
    check_one_command_distance(out)
    if backend is not None:
        return _resolved_names(out, backend)
    backend = make_backend(out["sim"])
    try:
        return _resolved_names(out, backend)
    finally:
        close_backend(backend)


def _resolved_names(out: dict, backend: Any) -> dict:
    """``out`` (checked by ``resolve_config``) with its towns resolved by ``backend`` (paths made absolute)
    and its towns and weathers checked against what the backend knows."""
    sim = out["sim"]["name"]
    known = list(backend.towns())
    if not out["towns"]:
        raise CollectConfigError(f"collect.towns is empty; known towns (sim={sim}): {', '.join(known)}")
    resolve = getattr(backend, "resolve_town", None)
    towns = []
    for t in out["towns"]:
        if resolve is not None:
            try:  # the backend's own error: unknown name, no such file, a broken file
                towns.append(str(resolve(t)))
            except ValueError as err:
                if t not in str(err) and Path(t).name not in str(err):
                    raise  # not about this town (e.g. a simulator server that does not answer)
                raise CollectConfigError(f"collect.towns: {err}", key="collect.towns", value=t) from None
        elif t in known:
            towns.append(t)
        else:
            raise CollectConfigError(f"collect.towns: unknown town {t!r}; known towns (sim={sim}): {', '.join(known)}",
                                     key="collect.towns", value=t)
    out["towns"] = towns
    keys = [town_key(t) for t in towns]
    dup = sorted({k for k in keys if keys.count(k) > 1})
    if dup:
        raise CollectConfigError(f"collect.towns: two towns named {dup[0]!r} (file names use a town file's stem); "
                                 f"rename one of the files", key="collect.towns", value=dup[0])
    known_w = list(backend.weathers())
    if not out["weathers"]:
        raise CollectConfigError(f"collect.weathers is empty; known weathers (sim={sim}): {', '.join(known_w)}")
    for w in out["weathers"]:
        if w not in known_w:
            raise CollectConfigError(f"collect.weathers: unknown weather {w!r}; known weathers (sim={sim}): "
                                     f"{', '.join(known_w)}")
    twice = sorted({w for w in out["weathers"] if out["weathers"].count(w) > 1})
    if twice:  # as a town listed twice: the metadata would list it twice and its episodes would repeat
        raise CollectConfigError(f"collect.weathers lists {twice[0]!r} twice; list each weather once",
                                 key="collect.weathers", value=twice[0])
    return out


def check_one_command_distance(out: dict) -> None:
    """A collection places its commands at its own ``command_distance``; the backend's ``sim.command_distance``
    (what the suite's routes use) is not read by it, so a value of its own there would be ignored without a
    word: refused, unless it is the backend's default or equals ``command_distance``."""
    theirs = out["sim"].get("command_distance")
    if theirs is None or (is_number(theirs) and any(math.isclose(float(theirs), v)
                                                  for v in (COMMAND_DISTANCE, float(out["command_distance"])))):
        return
    raise CollectConfigError(f"sim.command_distance={theirs} is not read by a collection: the collector places its "
                             f"commands at command_distance={out['command_distance']} (the collection's own key); "
                             f"give command_distance={theirs} instead", key="sim.command_distance", value=theirs)


def check_lock_wait(value: Any) -> None:
    """``lock_wait``: seconds >= 0, or None (wait as long as it takes)."""
    if value is not None and (not is_number(value) or value < 0):
        raise CollectConfigError(f"collect.lock_wait must be seconds >= 0 (0: refuse at once) or null "
                                 f"(wait as long as it takes), got {value!r}")


def config_hash(cfg: dict) -> str:
    """Hash of everything that shapes the data: the config but its runtime keys, the simulator's name
    when it is not the embedded one, the embedded simulator's weather family where it renders one of
    the weathers otherwise than before the families, and the contents of town files given by path."""
    keep = {k: v for k, v in cfg.items() if k not in _NOT_DATA}
    if cfg.get("sim", {}).get("name", "embedded") != "embedded":
        keep["sim"] = cfg["sim"]["name"]
    else:
        tag = family_data_tag(cfg["weathers"], cfg.get("sim", {}).get("weather_family", DEFAULT_FAMILY))
        if tag:
            keep["weather_family"] = tag
    files = {t: hashlib.sha256(Path(t).read_bytes()).hexdigest() for t in cfg["towns"] if _is_path(t)}
    if files:
        keep["town_files"] = files
    return hashlib.sha256(json.dumps(keep, sort_keys=True).encode()).hexdigest()[:16]


SAMPLE_BYTES = int(np.prod(IMAGE_SHAPE)) + 4 * N_TARGETS  # one sample in a CIL file, before HDF5's overhead


def episode_plan(cfg: dict) -> list[dict]:
    """Every episode's id, town, weather and seed: a pure function of the config."""
    combos = [(t, w) for t in cfg["towns"] for w in cfg["weathers"]]
    plan = []
    for i in range(cfg["episodes"]):
        town, weather = combos[i % len(combos)]
        plan.append({"id": f"ep{i:04d}_{town_key(town)}_{weather}", "index": i, "town": town, "weather": weather,
                     "seed": int(np.random.SeedSequence([int(cfg["seed"]), i]).generate_state(1)[0])})
    return plan


def steps_per_episode(cfg: dict) -> int:
    return int(round(float(cfg["seconds"]) * 10))


def episode_bytes(cfg: dict) -> int:
    """About what one episode's files take on disk (HDF5 overhead included, rounded up)."""
    n = steps_per_episode(cfg) * len(cfg["cameras"])
    parts = -(-n // SAMPLES_PER_FILE)
    return int(n * SAMPLE_BYTES * 1.01) + parts * 64 * 1024 + 64 * 1024
