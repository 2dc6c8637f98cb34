"""Collect a CIL HDF5 dataset with the embedded simulator: ``python -m cicfw.collect``.

Episodes drive random multi-junction routes (turns drawn to keep left / right / straight balanced)
in the chosen towns and weathers with the expert and CIL's steering noise; each step writes the
three cameras as three samples. Files: ``<episode>_<part>.h5`` (200 samples each, the last part of an
episode may be shorter), one JSON marker per finished episode under ``.episodes/``, and
``dataset_metadata.json`` (towns, weathers, seeds, sim version, counts, file -> episode). Resumable:
finished episodes are skipped; every file is written to a temporary name and renamed, and an
episode's files only get their final ``.h5`` names once all of them are written.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import numpy as np

from cicfw import __version__
from cicfw.data.cil_hdf5 import IMAGE_SHAPE, N_TARGETS, SAMPLES_PER_FILE, T, write_file

log = logging.getLogger(__name__)

SIM_VERSION = "embedded-1"  # bump when the simulator's output changes for the same config
CAMERA_IDS = {"centre": (0, 0.0), "left": (1, -30.0), "right": (2, 30.0)}  # name -> (targets[26], [27])

DEFAULTS: dict[str, Any] = {
    "towns": ["town_a"],
    "weathers": ["ClearNoon", "ClearSunset"],
    "episodes": 36,  # in total, spread round-robin over towns x weathers
    "seconds": 40.0,  # per episode (10 steps a second)
    "seed": 0,
    "cameras": ["centre", "left", "right"],
    "noise": {"episode_fraction": 0.75, "frequency": 15, "intensity": 10.0},
    "expert": {},  # overrides of cicfw.sim.expert.ExpertParams (cruise_kmh, lateral_accel ...)
    "command_distance": 12.0,  # metres before a junction where its turn command starts
    "workers": 2,  # processes; 0 or 1 = in this process
}


class CollectConfigError(ValueError):
    """A bad ``collect`` config value; the message names the key and what is accepted."""


def resolve_config(cfg: Any) -> dict:
    """The collect config as a plain dict over DEFAULTS, validated (one clear error per bad key)."""
    if cfg is None:
        cfg = {}
    if not isinstance(cfg, dict):
        from omegaconf import OmegaConf

        cfg = OmegaConf.to_container(cfg, resolve=True)
    cfg = {k: v for k, v in cfg.items() if k not in ("out_dir", "hydra")}
    unknown = sorted(set(cfg) - set(DEFAULTS))
    if unknown:
        raise CollectConfigError(f"collect: unknown key {unknown[0]!r}; accepted keys: {', '.join(DEFAULTS)}")
    out = json.loads(json.dumps(DEFAULTS))
    for k, v in cfg.items():
        if isinstance(out[k], dict):
            if not isinstance(v, dict):
                raise CollectConfigError(f"collect.{k} must be a mapping, got {v!r}")
            out[k].update(v)
        else:
            out[k] = v
    from cicfw.sim.expert import ExpertParams
    from cicfw.sim.town import town_names, town_path

    for t in out["towns"]:
        town_path(t)  # raises a TownError naming the shipped towns
    if not out["towns"]:
        raise CollectConfigError(f"collect.towns is empty; shipped towns: {', '.join(town_names())}")
    for c in out["cameras"]:
        if c not in CAMERA_IDS:
            raise CollectConfigError(f"collect.cameras: unknown camera {c!r}; known: {', '.join(CAMERA_IDS)}")
    try:
        from cicfw.sim.render import WEATHERS

        for w in out["weathers"]:
            if w not in WEATHERS:
                raise CollectConfigError(f"collect.weathers: unknown weather {w!r}; known: {', '.join(WEATHERS)}")
    except ImportError:
        pass
    if not out["weathers"]:
        raise CollectConfigError("collect.weathers is empty")
    if not isinstance(out["episodes"], int) or out["episodes"] < 1:
        raise CollectConfigError(f"collect.episodes must be an int >= 1, got {out['episodes']!r}")
    if not isinstance(out["seconds"], (int, float)) or out["seconds"] < 1:
        raise CollectConfigError(f"collect.seconds must be >= 1, got {out['seconds']!r}")
    extra = sorted(set(out["expert"]) - set(asdict(ExpertParams())))
    if extra:
        raise CollectConfigError(f"collect.expert: unknown key {extra[0]!r}; accepted: "
                                 f"{', '.join(asdict(ExpertParams()))}")
    extra = sorted(set(out["noise"]) - set(DEFAULTS["noise"]))
    if extra:
        raise CollectConfigError(f"collect.noise: unknown key {extra[0]!r}; accepted: {', '.join(DEFAULTS['noise'])}")
    if not 0.0 <= float(out["noise"]["episode_fraction"]) <= 1.0:
        raise CollectConfigError("collect.noise.episode_fraction must be in [0, 1]")
    return out


def episode_plan(cfg: dict) -> list[dict]:
    """Every episode's id, town, weather and seed: a pure function of the config."""
    combos = [(t, w) for t in cfg["towns"] for w in cfg["weathers"]]
    plan = []
    for i in range(cfg["episodes"]):
        town, weather = combos[i % len(combos)]
        plan.append({"id": f"ep{i:04d}_{town}_{weather}", "index": i, "town": town, "weather": weather,
                     "seed": int(np.random.SeedSequence([int(cfg["seed"]), i]).generate_state(1)[0])})
    return plan


def run_episode(cfg: dict, ep: dict, out_dir: Path) -> dict:
    """Drive one episode and write its files; returns its marker (files, counts, route)."""
    from cicfw.sim.env import DrivingEnv
    from cicfw.sim.expert import ExpertParams, Noiser
    from cicfw.sim.roadgraph import road_graph
    from cicfw.sim.town import load_town

    rng = np.random.default_rng(ep["seed"])
    town = load_town(ep["town"])
    graph = road_graph(town, float(cfg["command_distance"]))
    params = ExpertParams(**cfg["expert"])
    steps = int(round(float(cfg["seconds"]) * 10))
    route = graph.random_route(rng, min_length=steps * 0.1 * params.cruise_kmh / 3.6 + 30.0, name=ep["id"],
                               counts={})
    nz = cfg["noise"]
    noisy_episode = bool(rng.random() < float(nz["episode_fraction"]))
    noiser = Noiser(np.random.default_rng(rng.integers(2**63)), frequency=int(nz["frequency"]),
                    intensity=float(nz["intensity"]), enabled=noisy_episode)
    cams = list(cfg["cameras"])
    # one renderer per (town, weather) for the whole dataset (baking its textures takes seconds);
    # episodes differ in their rain phase through the time offset
    env = DrivingEnv(town, route, weather=ep["weather"], seed=int(cfg["seed"]), cameras=tuple(cams),
                     renderer=True, expert=params, timeout=1e9, max_deviation=1e9, success_radius=-1.0,
                     time_offset=float(ep["seed"] % 100_000) * 0.1)
    obs = env.reset()
    nc = len(cams)
    rgb = np.empty((steps * nc, *IMAGE_SHAPE), np.uint8)
    tg = np.zeros((steps * nc, N_TARGETS), np.float32)
    n = 0
    for k in range(steps):
        s = env.vehicle.s
        steer, v_kmh = env.expert_action()
        applied, flag = noiser.step(steer, s.speed_kmh)
        throttle, brake = env.speed_ctl(s.speed, v_kmh / 3.6)
        in_j, opp, off, _ = env.map.query(*env.vehicle.centre(), s.yaw, env.vehicle_params.width / 2)
        vx0, vy0 = s.speed * np.cos(s.yaw), s.speed * np.sin(s.yaw)
        row = np.zeros(N_TARGETS, np.float32)
        row[T.STEER], row[T.GAS], row[T.BRAKE] = steer, throttle, brake
        row[T.STEER_NOISE], row[T.GAS_NOISE], row[T.BRAKE_NOISE] = applied, throttle, brake
        row[T.POS_X], row[T.POS_Y] = s.x, s.y
        row[T.SPEED] = s.speed_kmh
        row[T.OPPOSITE_LANE], row[T.SIDEWALK] = opp, off
        row[T.PLATFORM_TIME] = row[T.GAME_TIME] = round(env.t * 1000.0)
        row[T.ORIENT_X], row[T.ORIENT_Y], row[T.ORIENT_Z] = np.cos(s.yaw), np.sin(s.yaw), 0.0
        row[T.COMMAND] = obs["command"]
        row[T.NOISE_FLAG] = float(flag)
        images = obs["images"]
        # step with the applied (noisy) steering through the throttle/brake just computed
        obs, _, _ = env.step(applied, throttle=throttle, brake=brake)
        s1 = env.vehicle.s
        row[T.ACC_X] = (s1.speed * np.cos(s1.yaw) - vx0) / 0.1
        row[T.ACC_Y] = (s1.speed * np.sin(s1.yaw) - vy0) / 0.1
        for c in cams:
            cid, yaw = CAMERA_IDS[c]
            tg[n] = row
            tg[n, T.CAMERA_ID], tg[n, T.CAMERA_YAW] = cid, yaw
            rgb[n] = images[c]
            n += 1
    # write the parts under temporary names, then give them their final names
    files = []
    parts = []
    for p, a in enumerate(range(0, n, SAMPLES_PER_FILE)):
        name = f"{ep['id']}_{p:03d}.h5"
        tmp = out_dir / f".{name}.part"
        write_file(tmp, rgb[a:a + SAMPLES_PER_FILE], tg[a:a + SAMPLES_PER_FILE])
        parts.append((tmp, out_dir / name))
        files.append({"name": name, "samples": int(min(SAMPLES_PER_FILE, n - a))})
    for tmp, final in parts:
        os.replace(tmp, final)
    cmds = tg[::nc, T.COMMAND].astype(int)
    marker = {**ep, "files": files, "samples": n, "steps": steps, "noisy_episode": noisy_episode,
              "noisy_steps": int(tg[::nc, T.NOISE_FLAG].sum()), "route_length_m": round(route.length, 1),
              "distance_driven_m": round(float(tg[::nc, T.SPEED].sum() / 3.6 * 0.1), 1),
              "commands": {str(c): int((cmds == c).sum()) for c in (2, 3, 4, 5)},
              "turns": [c for _, c, _, _ in route.turns]}
    _write_json(out_dir / ".episodes" / f"{ep['id']}.json", marker)
    return marker


def _write_json(path: Path, obj: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.write_text(json.dumps(obj, indent=1, sort_keys=True))
    os.replace(tmp, path)


def _config_hash(cfg: dict) -> str:
    keep = {k: v for k, v in cfg.items() if k != "workers"}
    return hashlib.sha256(json.dumps(keep, sort_keys=True).encode()).hexdigest()[:16]


def _clean_partials(out_dir: Path) -> int:
    """Remove what a killed run left half-written (temporary names only; finished files stay)."""
    n = 0
    for p in list(out_dir.glob(".*.part")) + list(out_dir.glob(".*.tmp")) + list(out_dir.glob(".episodes/.*")):
        p.unlink(missing_ok=True)
        n += 1
    return n


def _write_metadata(cfg: dict, out_dir: Path, plan: list[dict], markers: dict, started: float) -> Path:
    counts = {"episodes": len(markers), "samples": sum(m["samples"] for m in markers.values()),
              "steps": sum(m["steps"] for m in markers.values()),
              "files": sum(len(m["files"]) for m in markers.values()),
              "noisy_steps": sum(m["noisy_steps"] for m in markers.values())}
    cmd = {c: sum(m["commands"][c] for m in markers.values()) for c in ("2", "3", "4", "5")}
    meta = {
        "format": "CIL HDF5 (CoRL-2017 layout), written by cicfw.collect",
        "complete": len(markers) == len(plan),
        "cicfw_version": __version__, "sim_version": SIM_VERSION, "config_hash": _config_hash(cfg),
        "config": cfg, "towns": cfg["towns"], "weathers": cfg["weathers"], "seed": cfg["seed"],
        "cameras": {c: {"id": CAMERA_IDS[c][0], "yaw_deg": CAMERA_IDS[c][1]} for c in cfg["cameras"]},
        "counts": counts, "step_commands": cmd,
        "units": {"speed": "km/h", "position": "m (rear axle)", "time": "ms of game time",
                  "steer": "[-1, 1], positive right; targets[5] = steering applied (expert + noise)"},
        "episodes": {k: {x: m[x] for x in ("town", "weather", "seed", "samples", "noisy_episode",
                                            "noisy_steps", "route_length_m", "distance_driven_m", "commands")}
                     for k, m in sorted(markers.items())},
        "files": {f["name"]: {"episode": k, "samples": f["samples"]}
                  for k, m in sorted(markers.items()) for f in m["files"]},
        "collection_seconds": round(time.time() - started, 1),
    }
    path = out_dir / "dataset_metadata.json"
    _write_json(path, meta)
    return path


def collect_dataset(cfg_collect: Any, out_dir: str | Path, progress: bool = True) -> Path:
    """Collect (or finish collecting) a dataset into ``out_dir``; returns the metadata JSON path.

    ``cfg_collect``: a dict / DictConfig with any of DEFAULTS' keys (missing ones take the default).
    A rerun with the same config skips finished episodes; a different config in a folder that holds
    finished episodes is an error (use another folder).
    """
    cfg = resolve_config(cfg_collect)
    out_dir = Path(out_dir).expanduser().resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    _clean_partials(out_dir)
    meta_path = out_dir / "dataset_metadata.json"
    if meta_path.exists():
        old = json.loads(meta_path.read_text())
        if old.get("config_hash") != _config_hash(cfg):
            raise CollectConfigError(
                f"{out_dir} holds a dataset collected with another config (hash {old.get('config_hash')} "
                f"!= {_config_hash(cfg)}); collect into another folder or delete this one")
    plan = episode_plan(cfg)
    markers: dict[str, dict] = {}
    for ep in plan:
        mp = out_dir / ".episodes" / f"{ep['id']}.json"
        if mp.exists():
            m = json.loads(mp.read_text())
            if all((out_dir / f["name"]).exists() for f in m["files"]):
                markers[ep["id"]] = m
    todo = [ep for ep in plan if ep["id"] not in markers]
    started = time.time()
    if not todo:
        if not meta_path.exists() or not json.loads(meta_path.read_text()).get("complete"):
            return _write_metadata(cfg, out_dir, plan, markers, started)
        return meta_path
    log.info("collecting %d episode(s) (%d already done) into %s", len(todo), len(markers), out_dir)
    steps_per_ep = int(round(float(cfg["seconds"]) * 10))
    total_samples = len(todo) * steps_per_ep * len(cfg["cameras"])
    workers = int(cfg["workers"])
    bar = _Progress(progress, total_samples, f"collect {out_dir.name}")
    try:
        if workers <= 1:
            for ep in todo:
                m = run_episode(cfg, ep, out_dir)
                markers[ep["id"]] = m
                _write_metadata(cfg, out_dir, plan, markers, started)
                bar.advance(m["samples"])
        else:
            with ProcessPoolExecutor(max_workers=min(workers, len(todo)), mp_context=get_context("spawn")) as pool:
                futs = [pool.submit(run_episode, cfg, ep, out_dir) for ep in todo]
                for f in futs:
                    m = f.result()
                    markers[m["id"]] = m
                    _write_metadata(cfg, out_dir, plan, markers, started)
                    bar.advance(m["samples"])
    finally:
        bar.close()
    return _write_metadata(cfg, out_dir, plan, markers, started)


class _Progress:
    """A rich progress bar in samples (silent when disabled or not a terminal-friendly context)."""

    def __init__(self, enabled: bool, total: int, label: str) -> None:
        self.p = None
        if enabled:
            from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn,
                                       TimeElapsedColumn, TimeRemainingColumn)

            self.p = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                              TextColumn("samples"), TimeElapsedColumn(), TimeRemainingColumn())
            self.p.start()
            self.task = self.p.add_task(label, total=total)

    def advance(self, n: int) -> None:
        if self.p is not None:
            self.p.advance(self.task, n)

    def close(self) -> None:
        if self.p is not None:
            self.p.stop()


def _main() -> None:
    import hydra
    from omegaconf import DictConfig

    @hydra.main(version_base="1.3", config_path="pkg://cicfw.conf", config_name="collect")
    def main(cfg: DictConfig) -> None:
        out_dir = Path(cfg.out_dir).expanduser()
        meta = collect_dataset(cfg, out_dir)
        m = json.loads(meta.read_text())
        print(f"dataset: {out_dir} ({m['counts']['samples']} samples, {m['counts']['episodes']} episodes, "
              f"complete={m['complete']})")

    main()


if __name__ == "__main__":
    _main()
