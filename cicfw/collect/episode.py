"""One episode: the expert drives a random route with CIL's steering noise; its samples go to CIL files,
then its marker."""
from __future__ import annotations

import hashlib
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

from cicfw.collect.config import CAMERA_IDS, episode_bytes, steps_per_episode
from cicfw.collect.writing import check_free_space, write_files, write_json
from cicfw.data import cil_hdf5
from cicfw.data.cil_hdf5 import IMAGE_SHAPE, N_TARGETS, SAMPLES_PER_FILE, T
from cicfw.sim.expert import ExpertParams, Noiser


class ParentGone(Exception):
    """The collector that started this worker is gone: the episode is dropped, not finalised."""


def parent_alive(parent_pid: int | None) -> bool:
    """True in the collector's own process (``None``) or while a worker's parent is still its parent."""
    return parent_pid is None or os.getppid() == parent_pid


def _close_env(env: Any, exc: tuple) -> None:
    if hasattr(env, "__exit__"):
        env.__exit__(*exc)
    elif hasattr(env, "close"):
        env.close()


def run_episode(cfg: dict, ep: dict, out_dir: Path, backend: Any, parent_pid: int | None = None) -> dict:
    """Drive one episode and write its files; returns its marker (files, counts, route).

    ``parent_pid``: in a worker, the collector's pid; the episode is dropped if the collector is gone."""
    out_dir = Path(out_dir)
    check_free_space(out_dir, episode_bytes(cfg), f"episode {ep['id']}")
    rng = np.random.default_rng(ep["seed"])
    params = ExpertParams(**cfg["expert"])
    steps = steps_per_episode(cfg)
    route = backend.random_route(ep["town"], rng, steps * 0.1 * params.cruise_kmh / 3.6 + 30.0, name=ep["id"],
                                 command_distance=float(cfg["command_distance"]))
    nz = cfg["noise"]
    noisy_episode = bool(rng.random() < float(nz["episode_fraction"]))
    noiser = Noiser(np.random.default_rng(rng.integers(2**63)), frequency=int(nz["frequency"]),
                    intensity=float(nz["intensity"]), enabled=noisy_episode)
    cams = list(cfg["cameras"])
    # one renderer per (town, weather) for the whole dataset (baking its textures takes seconds);
    # episodes differ in their rain phase through the time offset
    env = backend.make_env(ep["town"], route, ep["weather"], seed=int(cfg["seed"]), cameras=tuple(cams),
                           renderer=True, expert=dict(cfg["expert"]),
                           time_offset=float(ep["seed"] % 100_000) * 0.1, endless=True)
    if hasattr(env, "__enter__"):
        env = env.__enter__() or env
    exc: tuple = (None, None, None)
    try:
        obs = env.reset()
        first = env.info() if hasattr(env, "info") else {}
        lane = (float(first.get("opposite_lane", 0.0)), float(first.get("off_road", 0.0)))
        nc = len(cams)
        rgb = np.empty((steps * nc, *IMAGE_SHAPE), np.uint8)
        tg = np.zeros((steps * nc, N_TARGETS), np.float32)
        n = 0
        for _ in range(steps):
            x, y, yaw = obs["pose"]
            speed = float(obs["speed_kmh"]) / 3.6
            steer, v_kmh = env.expert_action()
            applied, flag = noiser.step(steer, speed * 3.6)
            throttle, brake = env.speed_ctl(speed, v_kmh / 3.6)
            vx0, vy0 = speed * np.cos(yaw), speed * np.sin(yaw)
            row = np.zeros(N_TARGETS, np.float32)
            row[T.STEER], row[T.GAS], row[T.BRAKE] = steer, throttle, brake
            row[T.STEER_NOISE], row[T.GAS_NOISE], row[T.BRAKE_NOISE] = applied, throttle, brake
            row[T.POS_X], row[T.POS_Y] = x, y
            row[T.SPEED] = obs["speed_kmh"]
            row[T.OPPOSITE_LANE], row[T.SIDEWALK] = lane
            row[T.PLATFORM_TIME] = row[T.GAME_TIME] = round(float(obs["t"]) * 1000.0)
            row[T.ORIENT_X], row[T.ORIENT_Y], row[T.ORIENT_Z] = np.cos(yaw), np.sin(yaw), 0.0
            row[T.COMMAND] = obs["command"]
            row[T.NOISE_FLAG] = float(flag)
            images = obs["images"]
            # step with the applied (noisy) steering through the throttle/brake just computed
            obs, done, info = env.step(applied, throttle=throttle, brake=brake)
            lane = (float(info.get("opposite_lane", 0.0)), float(info.get("off_road", 0.0)))
            s1 = float(obs["speed_kmh"]) / 3.6
            yaw1 = obs["pose"][2]
            row[T.ACC_X] = (s1 * np.cos(yaw1) - vx0) / 0.1
            row[T.ACC_Y] = (s1 * np.sin(yaw1) - vy0) / 0.1
            for c in cams:
                cid, cyaw = CAMERA_IDS[c]
                tg[n] = row
                tg[n, T.CAMERA_ID], tg[n, T.CAMERA_YAW] = cid, cyaw
                rgb[n] = images[c]
                n += 1
            if done:
                break
    except BaseException:
        exc = sys.exc_info()
        raise
    finally:
        _close_env(env, exc)
    rgb, tg = rgb[:n], tg[:n]
    files = write_episode_files(out_dir, ep["id"], rgb, tg, parent_pid)
    cmds = tg[::nc, T.COMMAND].astype(int)
    marker = {**ep, "files": files, "samples": n, "steps": n // nc, "noisy_episode": noisy_episode,
              "noisy_steps": int(tg[::nc, T.NOISE_FLAG].sum()), "route_length_m": round(route.length, 1),
              "distance_driven_m": round(float(tg[::nc, T.SPEED].sum() / 3.6 * 0.1), 1),
              "commands": {str(c): int((cmds == c).sum()) for c in (2, 3, 4, 5)},
              "turns": [c for _, c, _, _ in route.turns], "config_hash": cfg.get("_hash")}
    if not parent_alive(parent_pid):
        raise ParentGone()
    write_json(out_dir / ".episodes" / f"{ep['id']}.json", marker)
    return marker


def write_episode_files(out_dir: Path, ep_id: str, rgb: np.ndarray, tg: np.ndarray,
                        parent_pid: int | None = None) -> list[dict]:
    """An episode's parts under temporary names, then (all written, the collector still there) under
    their final names. Each part's bytes are built as it is written: one part in memory at a time."""
    files: list[dict] = []

    def parts():
        for p, a in enumerate(range(0, len(tg), SAMPLES_PER_FILE)):
            name = f"{ep_id}_{p:03d}.h5"
            data = cil_hdf5.file_bytes(rgb[a:a + SAMPLES_PER_FILE], tg[a:a + SAMPLES_PER_FILE])
            files.append({"name": name, "samples": int(min(SAMPLES_PER_FILE, len(tg) - a)), "bytes": len(data),
                          "sha256": hashlib.sha256(data).hexdigest()})
            yield out_dir / name, data

    def collector_alive():
        if not parent_alive(parent_pid):
            raise ParentGone()

    write_files(parts(), before_rename=collector_alive)
    for f in files:  # the file as hashed: a reader may reuse the SHA-256 while size and mtime still match
        f["mtime_ns"] = (out_dir / f["name"]).stat().st_mtime_ns
    return files
