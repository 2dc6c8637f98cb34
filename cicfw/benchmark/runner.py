"""The lockstep runner: every episode of a run advances together, one batched policy call per step.

Each step gathers the observations of all running episodes, calls ``policy.act`` once per chunk of
``batch_size`` episodes, then advances every episode's simulator by one 0.1 s step with that steering
and the speed controller's throttle/brake (so the suite measures steering only). Episodes end on
success (within the backend's success radius of the goal), at their timeout, far off their route,
or once the car has spent more than ``off_road_s`` seconds (in total) with its centre off the road.
An episode is decided by the step that ends it and leaves the batch at once: it is never stepped or
acted on again, and the frame after its last step is not rendered either (an env whose ``step`` takes
``render=False`` renders with ``render()`` only for the episodes that go on), so a policy that reads a
camera costs one rendered frame per observation it is served, no more.
``workers`` > 1 splits the episodes over processes (spawned; each builds its own policy and
simulator from plain config); results are merged in episode order, so a run is deterministic for a
seed, batch size and worker count.
"""
from __future__ import annotations

import contextlib
import inspect
import math
import multiprocessing as mp
import os
import queue as queue_mod
import threading
import time
import traceback
from dataclasses import asdict, dataclass, field
from typing import Any, Callable, Mapping, Sequence

import cv2
import numpy as np
import torch

from cicfw.benchmark.policy import Observations, Policy, make_policy
from cicfw.benchmark.suite import Episode, make_backend, suite_routes
from cicfw.core.config_checks import is_integer
from cicfw.core.errors import USER_ERRORS, CicfwError, ConfigError
from cicfw.core.progress import ProgressBar
from cicfw.core.spawning import refused_by_worker
from cicfw.model.checkpoint import CheckpointBytes
from cicfw.registry import SIM_BACKENDS
from cicfw.sim.vehicle import TOP_SPEED_KMH

#: the simulator's reasons mapped to the report's (the embedded env calls "far off route" "lost")
REASONS = {"success": "success", "timeout": "timeout", "lost": "off_route", "off_route": "off_route",
           "off_road": "off_road"}
#: per-step trajectory channels recorded for every episode (maps, videos)
TRAJ_FIELDS = ("x", "y", "yaw", "speed_kmh", "steer", "command", "off_road", "opposite_lane")


@dataclass
class RunnerConfig:
    batch_size: int = 64  # episodes per policy call (a chunk); the network's batch
    workers: int | str | list = 1  # processes, or "auto" (see resolve_workers); CARLA: server ports
    seed: int = 0  # renderer seed (rain animation); the rest is deterministic
    off_road_s: float = 3.0  # end as "off_road" after more than this many seconds off the road in total
    off_road_level: float = 0.5  # off-road fraction of the car's width that counts (0.5: its centre is off)
    target_speed_kmh: float | None = None  # None: the planner's speed profile (slows for the turn)
    threads: int | None = None  # torch threads per worker, >= 1 (None: cores // workers)
    progress_bar: bool = True

    def __post_init__(self) -> None:
        if int(self.batch_size) < 1:
            raise CicfwError(f"runner.batch_size must be >= 1, got {self.batch_size}", key="runner.batch_size",
                             value=self.batch_size)
        if isinstance(self.workers, (list, tuple)):  # one simulator server per worker (sim=carla)
            if not self.workers or not all(isinstance(p, int) and 0 < p < 65536 for p in self.workers) \
                    or len(set(self.workers)) < len(self.workers):
                raise CicfwError(f"runner.workers as a list must hold distinct server ports (one CARLA "
                                 f"server each), e.g. [2000,2002]; got {self.workers!r}", key="runner.workers",
                                 value=self.workers)
        elif self.workers != "auto" and not (isinstance(self.workers, int) and self.workers >= 1):
            raise CicfwError(f"runner.workers must be an integer >= 1 or 'auto', got {self.workers!r} "
                             f"(with sim=carla: a list of server ports, one server each, e.g. [2000,2002])",
                             key="runner.workers", value=self.workers)
        # written so that NaN fails too: it passes any "<= 0" test and then silently disables the rule
        if not 0 < self.off_road_s < math.inf:
            raise ConfigError("runner.off_road_s", self.off_road_s, "a finite number of seconds > 0")
        if not 0 < self.off_road_level <= 1:
            raise ConfigError("runner.off_road_level", self.off_road_level, "a fraction of the car's width in (0, 1]")
        if self.target_speed_kmh is not None and not 0 < self.target_speed_kmh <= TOP_SPEED_KMH:
            raise ConfigError("runner.target_speed_kmh", self.target_speed_kmh,
                              f"a speed > 0 and at most {TOP_SPEED_KMH} km/h, the car's top speed (or null)")
        # 0 meant null (the cores / workers) without a word; as diagnose's threads, it is refused
        if self.threads is not None and not (is_integer(self.threads) and self.threads >= 1):
            raise ConfigError("runner.threads", self.threads, "null (the cores / workers) or an integer >= 1")


    def resolve_workers(self, episodes: Sequence[Episode], renders: bool) -> int:
        """The process count: as configured, or for "auto" one per core when the policy renders
        (rendering and inference then use every core), at most one per (town, weather) cell and
        one per 32 episodes (a process costs seconds to start); 1 for a policy that renders nothing."""
        if isinstance(self.workers, (list, tuple)):
            return min(len(self.workers), max(len(episodes), 1))
        if self.workers != "auto":
            return min(int(self.workers), max(len(episodes), 1))
        if not renders:
            return 1
        cells = len({(e.town, e.weather) for e in episodes})
        return max(1, min(os.cpu_count() or 1, cells, len(episodes) // 32))


@dataclass
class RunResult:
    rows: list[dict[str, Any]]  # one per episode, in episode order
    trajectories: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)  # key -> channel -> (T,)
    wall_s: float = 0.0
    steps: int = 0  # policy observations served (sum of episode lengths)


# ------------------------------------------------------------------------------------------------
# the lockstep core (one process)


class _Track:
    """What the runner keeps per running episode."""

    __slots__ = ("env", "obs", "route", "rec", "off_time", "dist", "last_xy", "on_demand")

    def __init__(self, env: Any, route: Any, cameras: tuple = ()) -> None:
        self.env, self.route = env, route
        # render a frame only once the episode is known to go on (an env that can: DrivingEnv)
        self.on_demand = bool(cameras) and renders_on_demand(env)
        self.rec: list[tuple] = []
        self.off_time = 0.0
        self.dist = 0.0


def drive(episodes: Sequence[Episode], policy: Policy, backend: Any, cfg: RunnerConfig,
          on_done: Callable[[dict, dict], None] | None = None) -> RunResult:
    """Run ``episodes`` with ``policy`` in this process: all in lockstep, or one after another for a
    backend whose server runs one episode at a time (``backend.lockstep`` false: CARLA). Such a
    backend is closed on any exit (its live episode's actors destroyed, its settings restored).
    ``on_done(row, trajectory)`` is called as each episode finishes."""
    if getattr(backend, "lockstep", True):
        return _lockstep(episodes, policy, backend, cfg, on_done)
    t0 = time.perf_counter()
    parts: list[RunResult] = []
    try:
        for ep in episodes:
            parts.append(_lockstep([ep], policy, backend, cfg, on_done))
    finally:
        close = getattr(backend, "close", None)
        if close is not None:
            close()
    return _merged(parts, t0)


def _merged(parts: Sequence[RunResult], t0: float) -> RunResult:
    """One result of several (an episode's, or a worker's), its rows in episode order."""
    return RunResult(rows=sorted((r for p in parts for r in p.rows), key=lambda r: r["episode"]),
                     trajectories={k: v for p in parts for k, v in p.trajectories.items()},
                     wall_s=time.perf_counter() - t0, steps=sum(p.steps for p in parts))


def _lockstep(episodes: Sequence[Episode], policy: Policy, backend: Any, cfg: RunnerConfig,
              on_done: Callable[[dict, dict], None] | None = None) -> RunResult:
    """Run ``episodes`` in lockstep with ``policy`` in this process."""
    t0 = time.perf_counter()
    cams = tuple(policy.cameras)
    tracks: list[_Track] = []
    for ep in episodes:
        route = suite_routes(backend, ep.town)[ep.pair]
        env = backend.make_env(ep.town, route, ep.weather, seed=cfg.seed, cameras=cams or ("centre",),
                               renderer=bool(cams))
        tr = _Track(env, route, cams)
        tr.obs = env.reset()
        tr.last_xy = tr.obs["pose"][:2]
        tracks.append(tr)
    policy.reset([ep.index for ep in episodes])
    active = list(range(len(episodes)))
    rows: dict[int, dict] = {}
    trajs: dict[str, dict[str, np.ndarray]] = {}
    steps = 0
    bs = int(cfg.batch_size)
    while active:
        steer = np.empty(len(episodes))
        for c0 in range(0, len(active), bs):
            chunk = active[c0:c0 + bs]
            steer[chunk] = _act(policy, [tracks[i] for i in chunk], [episodes[i].index for i in chunk], cams)
        steps += len(active)
        still = []
        for i in active:
            tr, ep = tracks[i], episodes[i]
            o = tr.obs
            target = cfg.target_speed_kmh if cfg.target_speed_kmh is not None else o["target_speed_kmh"]
            new, done, info = tr.env.step(float(steer[i]), target_speed_kmh=float(target),
                                          **({"render": False} if tr.on_demand else {}))
            x, y, yaw = o["pose"]
            tr.rec.append((x, y, yaw, o["speed_kmh"], steer[i], o["command"],
                           info.get("off_road", 0.0), info.get("opposite_lane", 0.0)))
            nx, ny = new["pose"][:2]
            tr.dist += math.hypot(nx - tr.last_xy[0], ny - tr.last_xy[1])
            tr.last_xy = (nx, ny)
            tr.obs = new
            reason = REASONS.get(info["reason"], info["reason"]) if done else None
            if reason is None:
                if info.get("off_road", 0.0) >= cfg.off_road_level:
                    tr.off_time += 0.1
                if tr.off_time > cfg.off_road_s + 1e-9:
                    reason = "off_road"
            if reason is None:
                if tr.on_demand:  # it goes on: the frame its policy will be served next
                    new["images"] = tr.env.render()
                still.append(i)
                continue
            rows[i], trajs[ep.key] = _finish(ep, tr, info, reason)
            tr.env = None  # free the episode's simulator
            if on_done is not None:
                on_done(rows[i], trajs[ep.key])
        active = still
    return RunResult(rows=[rows[i] for i in range(len(episodes))], trajectories=trajs,
                     wall_s=time.perf_counter() - t0, steps=steps)


def renders_on_demand(env: Any) -> bool:
    """Whether ``env.step`` takes ``render=False`` and ``env.render()`` draws the frame afterwards (the
    embedded simulator's env); a backend whose frames come with every tick (CARLA's sensors) has not."""
    step, render = getattr(env, "step", None), getattr(env, "render", None)
    if not callable(step) or not callable(render):
        return False
    try:
        return "render" in inspect.signature(step).parameters
    except (TypeError, ValueError):
        return False


def _act(policy: Policy, tracks: list[_Track], indices: list[int], cams: tuple) -> np.ndarray:
    obs = Observations(
        images={c: np.stack([t.obs["images"][c] for t in tracks]) for c in cams},
        speed_kmh=np.array([t.obs["speed_kmh"] for t in tracks], np.float32),
        command=np.array([t.obs["command"] for t in tracks], np.int64),
        pose=np.array([t.obs["pose"] for t in tracks], np.float64),
        routes=[t.route for t in tracks],
        episode=np.array(indices, np.int64),
    )
    steer = np.asarray(policy.act(obs), dtype=np.float64).reshape(-1)
    if steer.shape != (len(tracks),):
        raise ValueError(f"policy {policy.label!r}: act() returned {steer.size} values for a batch of "
                         f"{len(tracks)}; it must return one steering value per observation")
    if not np.all(np.isfinite(steer)):
        raise ValueError(f"policy {policy.label!r}: act() returned non-finite steering {steer[~np.isfinite(steer)][:3]}")
    return np.clip(steer, -1.0, 1.0)


def _finish(ep: Episode, tr: _Track, info: Mapping[str, Any], reason: str) -> tuple[dict, dict]:
    rec = np.array(tr.rec, np.float64).reshape(-1, len(TRAJ_FIELDS))
    traj = {name: rec[:, k].astype(np.float32) for k, name in enumerate(TRAJ_FIELDS)}
    traj["command"] = rec[:, 5].astype(np.int8)
    nx, ny = tr.last_xy
    traj["end"] = np.array([nx, ny], np.float32)
    row = {
        "episode": ep.index, "key": ep.key, "town": ep.key.split("/")[0], "weather": ep.weather,
        "town_set": ep.town_set, "weather_set": ep.weather_set, "pair": ep.pair, "route": ep.route,
        "command": ep.command, "success": reason == "success", "reason": reason,
        "time_s": round(float(info.get("t", len(rec) * 0.1)), 2),
        "timeout_s": round(float(tr.route.timeout()), 2),
        "distance_m": round(tr.dist, 2), "route_length_m": round(float(tr.route.length), 2),
        "goal_distance_m": round(float(info.get("distance_to_goal", float("nan"))), 2),
        "progress": round(float(info.get("progress", float("nan"))), 4),
        "offroad_fraction": round(float(rec[:, 6].mean()) if len(rec) else 0.0, 4),
        "opposite_lane_fraction": round(float(rec[:, 7].mean()) if len(rec) else 0.0, 4),
        "steps": len(rec),
    }
    return row, traj


# ------------------------------------------------------------------------------------------------
# progress, processes


class EpisodeBar(ProgressBar):
    """The project's progress bar over episodes, with the running success rate (nothing when disabled)."""

    def __init__(self, total: int, label: str, enabled: bool = True) -> None:
        super().__init__(enabled, total, label, "episodes, success {task.fields[rate]}", rate="-")
        self.done, self.ok = 0, 0

    def update(self, success: bool) -> None:
        """One more episode finished."""
        self.done += 1
        self.ok += bool(success)
        self.advance(rate=f"{100.0 * self.ok / self.done:.1f}%")


def run(episodes: Sequence[Episode], policy: Policy | Mapping[str, Any], sim: Any, cfg: RunnerConfig,
        label: str | None = None, on_episode: Callable[[dict, dict], None] | None = None) -> RunResult:
    """Run the episodes with a policy and a simulator backend, each an instance or its config spec
    (``{name:, ...}``). With ``cfg.workers > 1`` both must be specs: each process builds its own.
    ``on_episode(row, trajectory)`` is called in this process as each episode finishes (whichever
    worker drove it): the evaluation keeps finished episodes with it, so a killed run resumes.
    """
    episodes = list(episodes)
    workers = cfg.resolve_workers(episodes, renders=not isinstance(policy, Policy) or bool(policy.cameras))
    servers = server_specs(sim, cfg.workers)  # CARLA: one worker per server
    if servers is not None:
        workers = min(len(servers), max(len(episodes), 1))
        if workers == 1:
            sim = servers[0]
    specs = isinstance(policy, Mapping) and (sim is None or isinstance(sim, Mapping))
    if workers > 1 and not specs and cfg.workers == "auto":
        workers = 1
    if workers > 1 and not specs:
        raise ValueError("runner.workers > 1 needs the policy and the simulator as config specs "
                         "({name: ..., ...}) so each process can build its own")
    name = label or (policy.label if isinstance(policy, Policy) else str(policy.get("name")))
    bar = EpisodeBar(len(episodes), name, cfg.progress_bar)

    def done(row: dict, traj: dict) -> None:
        if on_episode is not None:
            on_episode(row, traj)
        bar.update(row["success"])

    try:
        if workers <= 1:
            pol = policy if isinstance(policy, Policy) else make_policy(policy)
            backend = make_backend(sim) if sim is None or isinstance(sim, Mapping) else sim
            with _torch_threads(cfg.threads):
                return drive(episodes, pol, backend, cfg, on_done=done)
        return _run_processes(episodes, dict(policy), dict(sim or {"name": "embedded"}), cfg, workers, done,
                              sims=servers)
    finally:
        bar.close()


def server_specs(sim: Any, workers: Any) -> list | None:
    """The simulator of each worker for a backend whose server runs one episode at a time (class
    attribute ``lockstep = False``: CARLA), None for the others (their workers are processes).

    Such a backend gets one worker per server: ``runner.workers`` is then a list of ports
    (``[2000,2002]``: the sim spec with each ``port``); 1 or "auto" is the configured server alone; a
    larger number would drive one server from several processes and is refused."""
    if sim is not None and not isinstance(sim, Mapping):
        cls, name = type(sim), type(sim).__name__
    else:
        name = str((sim or {}).get("name", "embedded"))
        cls = SIM_BACKENDS.get(name)
    ports = isinstance(workers, (list, tuple))
    if getattr(cls, "lockstep", True):
        if ports:
            raise CicfwError(f"runner.workers={list(workers)}: a list of server ports is for a simulator that "
                             f"runs one episode per server (sim=carla); sim={name} takes a number of processes "
                             f"or 'auto'", key="runner.workers", value=workers)
        return None
    if not ports:
        if workers not in ("auto", 1):
            raise CicfwError(f"runner.workers={workers}: sim={name} runs one episode at a time per server, so "
                             f"its workers are servers: give their ports, e.g. runner.workers=[2000,2002] (one "
                             f"server each), or 1", key="runner.workers", value=workers)
        return [sim]
    if not isinstance(sim, Mapping):
        if len(workers) == 1:
            return [sim]
        raise ValueError("runner.workers as a list of ports needs the simulator as a config spec ({name: ...})")
    return [{**sim, "port": int(p)} for p in workers]


@contextlib.contextmanager
def _torch_threads(n: int | None):
    """Use ``n`` torch threads inside the block (if given), then restore the caller's setting."""
    if not n:
        yield
        return

    before = torch.get_num_threads()
    torch.set_num_threads(int(n))
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _run_processes(episodes: list[Episode], policy_spec: dict, sim_spec: dict, cfg: RunnerConfig,
                   workers: int, done: Callable[[dict, dict], None], sims: list[dict] | None = None) -> RunResult:
    t0 = time.perf_counter()
    ctx = mp.get_context("spawn")  # fork after torch's thread pools started can deadlock
    q = ctx.Queue()
    threads = int(cfg.threads) if cfg.threads else max((os.cpu_count() or 1) // workers, 1)
    shards = shard(episodes, workers)
    procs = [ctx.Process(target=_worker, args=(k, shards[k], policy_spec, sims[k] if sims else sim_spec,
                                               asdict(cfg), threads, q), daemon=True) for k in range(workers)]
    for p in procs:
        p.start()
    results: dict[int, RunResult] = {}
    try:
        while len(results) < workers:
            try:
                msg = q.get(timeout=1.0)
            except queue_mod.Empty:
                dead = [k for k, p in enumerate(procs) if not p.is_alive() and k not in results]
                if dead and q.empty():
                    refused = refused_by_worker(procs[dead[0]].exitcode, "evaluate_policy", "runner.workers",
                                                cfg.workers)
                    if refused is not None:
                        raise refused
                    raise RuntimeError(f"evaluation worker {dead[0]} died (exit code "
                                       f"{procs[dead[0]].exitcode}) without a result")
                continue
            if msg[0] == "done":
                done(msg[2], msg[3])
            elif msg[0] == "result":
                results[msg[1]] = msg[2]
            elif msg[0] == "error":
                kind, text, tb = msg[2], msg[3], msg[4]
                if kind == "user error":
                    raise CicfwError(text)
                raise RuntimeError(f"evaluation worker {msg[1]} failed:\n{tb}")
    finally:
        for p in procs:
            if p.is_alive():
                p.terminate()
            p.join(timeout=5)
    return _merged([results[k] for k in sorted(results)], t0)


def shard(episodes: Sequence[Episode], workers: int) -> list[list[Episode]]:
    """Split episodes over workers. Whole (town, weather) cells go to one worker when there are at
    least as many cells as workers (a renderer bakes its textures per cell, seconds each), largest
    first onto the least loaded worker; otherwise episodes are dealt round-robin."""
    cells: dict[tuple[str, str], list[Episode]] = {}
    for e in episodes:
        cells.setdefault((e.town, e.weather), []).append(e)
    if len(cells) < workers:
        return [list(episodes[k::workers]) for k in range(workers)]
    shards: list[list[Episode]] = [[] for _ in range(workers)]
    for cell in sorted(cells.values(), key=len, reverse=True):
        min(shards, key=len).extend(cell)
    return [sorted(s, key=lambda e: e.index) for s in shards]


def _worker(k: int, episodes: list[Episode], policy_spec: dict, sim_spec: dict, cfg: dict, threads: int,
            q: Any) -> None:
    try:
        torch.set_num_threads(threads)
        cv2.setNumThreads(1)
        _exit_with_parent()
        rc = RunnerConfig(**{**cfg, "workers": 1, "progress_bar": False})
        policy = make_policy(policy_spec)
        # built: the checkpoint's bytes it was given (CheckpointBytes, the whole file with its optimizer state) are
        # not kept for the run, by the spec (which the Process object holds) or by the policy (its ``source``)
        policy_spec.clear()
        if isinstance(getattr(policy, "source", None), CheckpointBytes):
            policy.source = None
        res = drive(episodes, policy, make_backend(sim_spec), rc,
                    on_done=lambda row, traj: q.put(("done", k, row, traj)))
        q.put(("result", k, res))
    except BaseException as err:  # report everything, the parent decides
        kind = "user error" if isinstance(err, USER_ERRORS) else type(err).__name__
        q.put(("error", k, kind, str(err), traceback.format_exc()))


def _exit_with_parent(poll_s: float = 1.0) -> None:
    """End this worker process as soon as its parent is gone (a killed evaluation leaves no workers
    driving on; the rerun resumes from the episodes the parent kept). The parent is the process that
    started this one, so a parent killed while the worker was still importing torch counts too."""
    started_by = mp.parent_process()
    parent = started_by.pid if started_by is not None else os.getppid()

    def watch() -> None:
        while True:
            time.sleep(poll_s)
            if os.getppid() != parent:
                os._exit(1)

    threading.Thread(target=watch, name="cicfw-parent-watch", daemon=True).start()
