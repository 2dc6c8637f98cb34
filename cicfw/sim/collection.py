"""The data collection engine: a CIL HDF5 dataset from any simulator backend (``SIM_BACKENDS``).

``collect_dataset(cfg, out_dir)`` drives random multi-junction routes (turns drawn to keep left / right /
straight balanced) in the chosen towns and weathers with the expert and CIL's steering noise; each step
writes one sample per camera. Files: ``<episode>_<part>.h5`` (200 samples each, the last part of an
episode may be shorter), one JSON marker per finished episode under ``.episodes/``, and
``dataset_metadata.json`` (towns, weathers, seeds, sim version, counts, file -> episode). The app
``python -m cicfw.collect`` (``cicfw/collect.py``) is a thin shell around this module.

Guarantees (each has a fault test in ``tests/test_collect_integrity.py``):

- **One writer per folder.** The whole collection holds an exclusive ``fcntl.flock`` on
  ``<out_dir>/.collect.lock``, which records the holder (pid, host, start time, worker pids). A second
  collector (or a second training job filling the same default dataset) waits ``lock_wait`` seconds
  (``null``: as long as it takes) or refuses at once (``0``), with one line naming the holder. The kernel
  drops the lock when the holder dies, so a stale lock file never blocks anyone.
- **Nothing half-written, nothing mixed.** Every file is written under a temporary name unique to the
  process (``.<name>.<pid>-<random>.part`` / ``.tmp``) and renamed; an episode's files get their final
  names only when all of them are written, then its marker. The metadata (``complete: false``) is
  written before the first episode; a folder that holds another config's dataset, another simulator
  version's unfinished dataset, or HDF5 files this collection does not plan, is an error.
- **Workers die with their parent.** Worker processes ask the kernel for SIGKILL when their parent dies
  (``prctl(PR_SET_PDEATHSIG)`` on Linux) and poll their parent pid every second (everywhere); they also
  check it before giving any file its final name. A worker that dies is reported (exit code, episode).
- **A full disk is one clear error.** Free space is checked before anything is simulated (the whole
  remainder) and before each episode; files are built in memory (HDF5 into a ``BytesIO``) and written
  with plain ``os.write``, so ENOSPC is an ``OSError`` (never a crash inside HDF5), turned into
  ``DiskFullError`` after removing the episode's temporary files.
- **Reported before simulating:** every bad config value, an unwritable or unusable output folder.
- **``complete`` means complete:** true only when every planned episode has its marker and every file
  exists with its recorded size and SHA-256 (``sha256`` per file in the markers and in the metadata's
  ``files``; the episode files themselves are plain CIL files, unchanged). A rerun checks every file:
  one whose bytes changed after it was written (a flipped bit, an edit) is named in one warning and its
  episode is collected again (deterministic: the same bytes come back). Files of a dataset collected before
  checksums were kept are checked for size and layout (they open as CIL files with their recorded number
  of samples), and their checksums are recorded then. ``verify_dataset`` (``cicfw collect --verify``)
  checks a folder without changing it: one line per missing or corrupt file.

Backend interface (what the engine calls; ``EmbeddedBackend`` implements all of it)::

    backend = SIM_BACKENDS.get(name)(**kwargs)            # kwargs: conf/sim/<name>.yaml but ``name``
    backend.towns() -> list[str]                          # known town names (for error messages)
    backend.weathers() -> list[str]                       # known weather names
    backend.resolve_town(town) -> str                     # optional: a name, or a path -> its absolute
                                                          #   path; ValueError naming the known towns, a
                                                          #   missing file or the file's problem.
                                                          #   Without it: names in towns() only.
    backend.random_route(town, rng, min_length, name=, command_distance=) -> cicfw.sim.roadgraph.Route
    backend.make_env(town, route, weather, seed=, cameras=, renderer=True,
                     expert=dict, time_offset=float, endless=True) -> env
    backend.data_version -> str                           # optional: metadata's sim_version
    type(backend).worker_kwargs(kwargs, index) -> dict | None
                                                          # optional (class/static method): the backend
                                                          #   kwargs of worker ``index`` (e.g. one server
                                                          #   per worker); None: no worker of that index
                                                          #   (fewer workers). Without it: the same kwargs.
    env.reset() -> obs        # obs: images {camera: (88, 200, 3) uint8 RGB}, command (2-5),
                              #      speed_kmh, pose (x, y, yaw: metres, rear axle, our frame), t (s)
    env.expert_action() -> (steer in [-1, 1], target speed km/h)
    env.speed_ctl(speed m/s, target m/s) -> (throttle, brake)
    env.step(steer, throttle=, brake=) -> (obs, done, info)   # info: opposite_lane, off_road (0-1)
    env.info() -> info        # optional: the current state's info (lane fractions of the first step)
    env.close() / with env:   # optional: release the simulator's resources on any exit

An env that reports ``done`` before the episode's steps ends the episode early (shorter files).
Workers (``workers`` > 1) are spawned processes that each build their own backend; the parent
collects in-process when ``workers`` <= 1.
"""
from __future__ import annotations

import ctypes
import errno
import hashlib
import io
import json
import logging
import math
import os
import queue
import secrets
import shutil
import signal
import socket
import sys
import threading
import time
import traceback
from dataclasses import asdict
from multiprocessing import get_context
from pathlib import Path
from typing import Any, Callable

import numpy as np

from cicfw import __version__
from cicfw.data.cil_hdf5 import IMAGE_SHAPE, N_TARGETS, SAMPLES_PER_FILE, T, CILFormatError, check_file
from cicfw.registry import SIM_BACKENDS, UnknownNameError

log = logging.getLogger(__name__)

SIM_VERSION = "embedded-1"  # bump when the embedded simulator's output changes for the same config
CAMERA_IDS = {"centre": (0, 0.0), "left": (1, -30.0), "right": (2, 30.0)}  # name -> (targets[26], [27])
LOCK_NAME = ".collect.lock"
META_NAME = "dataset_metadata.json"
SAMPLE_BYTES = int(np.prod(IMAGE_SHAPE)) + 4 * N_TARGETS  # one sample in a CIL file, before HDF5's overhead

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
    "lock_wait": None,  # seconds to wait for another process collecting into the folder; None: wait
    "sim": {"name": "embedded"},  # the simulator backend: conf/sim/<name>.yaml
}
# keys that do not change the data (left out of the config hash, so a rerun may change them)
_NOT_DATA = ("workers", "lock_wait", "sim", "_hash")


class CollectError(ValueError):
    """A collection that cannot go on for a reason the user can fix; the message says what and how.

    A ``ValueError`` so that the apps' ``report_user_errors`` prints it as one line."""


class CollectConfigError(CollectError):
    """A bad ``collect`` config value; the message names the key and what is accepted."""


class FolderLockedError(CollectError):
    """The output folder is locked by another collector; the message names the holder."""


class DiskFullError(CollectError):
    """Not enough free space for the next episode, or a write failed with ENOSPC / EDQUOT."""


# ------------------------------------------------------------------------------------------------
# config


def _close_backend(backend: Any) -> None:
    if backend is not None and hasattr(backend, "close"):
        backend.close()


def _plain(cfg: Any) -> dict:
    if cfg is None:
        return {}
    if not isinstance(cfg, dict):
        from omegaconf import OmegaConf

        cfg = OmegaConf.to_container(cfg, resolve=True)
    if cfg.get("verify"):  # the app's switch (cicfw collect --verify): it never reaches a collection
        raise CollectConfigError("collect: verify=true checks a collected folder and is the collect app's switch "
                                 "(python -m cicfw.collect out_dir=... verify=true); a collection cannot take it")
    return {k: v for k, v in cfg.items() if k not in ("out_dir", "hydra", "verify")}


def _sim_node(cfg: dict) -> dict:
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


def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def resolve_config(cfg: Any, backend: Any = None) -> dict:
    """The collect config as a plain dict over DEFAULTS, validated (one clear error per bad key).

    Towns given by path come back as absolute paths. ``backend``: the sim backend, if already built
    (otherwise one is built for the check and closed)."""
    cfg = _plain(cfg)
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
    for k in ("towns", "weathers", "cameras"):
        if isinstance(out[k], str):
            out[k] = [out[k]]
        if not isinstance(out[k], (list, tuple)) or not all(isinstance(x, str) for x in out[k]):
            raise CollectConfigError(f"collect.{k} must be a list of names, got {out[k]!r}")
        out[k] = list(out[k])
    if not isinstance(out["episodes"], int) or isinstance(out["episodes"], bool) or out["episodes"] < 1:
        raise CollectConfigError(f"collect.episodes must be an integer >= 1, got {out['episodes']!r}")
    if not _number(out["seconds"]) or round(float(out["seconds"]) * 10) < 1:
        raise CollectConfigError(f"collect.seconds must be > 0 (at least 0.1: one step at 10 Hz), "
                                 f"got {out['seconds']!r}")
    if not isinstance(out["seed"], int) or isinstance(out["seed"], bool):
        raise CollectConfigError(f"collect.seed must be an integer, got {out['seed']!r}")
    if not isinstance(out["workers"], int) or isinstance(out["workers"], bool) or out["workers"] < 0:
        raise CollectConfigError(f"collect.workers must be an integer >= 0 (0 or 1: in this process), "
                                 f"got {out['workers']!r}")
    if out["lock_wait"] is not None and (not _number(out["lock_wait"]) or out["lock_wait"] < 0):
        raise CollectConfigError(f"collect.lock_wait must be seconds >= 0 (0: refuse at once) or null "
                                 f"(wait as long as it takes), got {out['lock_wait']!r}")
    if not _number(out["command_distance"]) or out["command_distance"] <= 0:
        raise CollectConfigError(f"collect.command_distance must be metres > 0, got {out['command_distance']!r}")
    if not out["cameras"]:
        raise CollectConfigError(f"collect.cameras is empty; known: {', '.join(CAMERA_IDS)}")
    for c in out["cameras"]:
        if c not in CAMERA_IDS:
            raise CollectConfigError(f"collect.cameras: unknown camera {c!r}; known: {', '.join(CAMERA_IDS)}")
    if len(set(out["cameras"])) != len(out["cameras"]):
        raise CollectConfigError(f"collect.cameras lists a camera twice: {out['cameras']}")
    nz = out["noise"]
    extra = sorted(set(nz) - set(DEFAULTS["noise"]))
    if extra:
        raise CollectConfigError(f"collect.noise: unknown key {extra[0]!r}; accepted: {', '.join(DEFAULTS['noise'])}")
    if not _number(nz["episode_fraction"]) or not 0.0 <= nz["episode_fraction"] <= 1.0:
        raise CollectConfigError(f"collect.noise.episode_fraction must be in [0, 1], got {nz['episode_fraction']!r}")
    if not isinstance(nz["frequency"], int) or isinstance(nz["frequency"], bool) or nz["frequency"] < 0:
        raise CollectConfigError(f"collect.noise.frequency must be an integer >= 0, got {nz['frequency']!r}")
    if not _number(nz["intensity"]) or nz["intensity"] < 0:
        raise CollectConfigError(f"collect.noise.intensity must be >= 0, got {nz['intensity']!r}")
    from cicfw.sim.expert import ExpertParams

    accepted = asdict(ExpertParams())
    extra = sorted(set(out["expert"]) - set(accepted))
    if extra:
        raise CollectConfigError(f"collect.expert: unknown key {extra[0]!r}; accepted: {', '.join(accepted)}")
    for k, v in out["expert"].items():
        if not _number(v):
            raise CollectConfigError(f"collect.expert.{k} must be a number, got {v!r}")
    out["sim"] = _sim_node(out)
    if backend is None:
        backend = make_backend(out["sim"])
        try:
            return resolve_config(out, backend)
        finally:
            _close_backend(backend)
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
                raise CollectConfigError(f"collect.towns: {err}") from None
        elif t in known:
            towns.append(t)
        else:
            raise CollectConfigError(f"collect.towns: unknown town {t!r}; known towns (sim={sim}): {', '.join(known)}")
    out["towns"] = towns
    keys = [town_key(t) for t in towns]
    dup = sorted({k for k in keys if keys.count(k) > 1})
    if dup:
        raise CollectConfigError(f"collect.towns: two towns named {dup[0]!r} (file names use a town file's stem); "
                                 f"rename one of the files")
    known_w = list(backend.weathers())
    if not out["weathers"]:
        raise CollectConfigError(f"collect.weathers is empty; known weathers (sim={sim}): {', '.join(known_w)}")
    for w in out["weathers"]:
        if w not in known_w:
            raise CollectConfigError(f"collect.weathers: unknown weather {w!r}; known weathers (sim={sim}): "
                                     f"{', '.join(known_w)}")
    return out


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


def config_hash(cfg: dict) -> str:
    """Hash of everything that shapes the data: the config but its runtime keys, the simulator's name
    when it is not the embedded one, and the contents of town files given by path."""
    keep = {k: v for k, v in cfg.items() if k not in _NOT_DATA}
    if cfg.get("sim", {}).get("name", "embedded") != "embedded":
        keep["sim"] = cfg["sim"]["name"]
    files = {t: hashlib.sha256(Path(t).read_bytes()).hexdigest() for t in cfg["towns"] if _is_path(t)}
    if files:
        keep["town_files"] = files
    return hashlib.sha256(json.dumps(keep, sort_keys=True).encode()).hexdigest()[:16]


# ------------------------------------------------------------------------------------------------
# writing: temporary names unique to the process, bytes built in memory, one clear error on a full disk


def _tmp_name(path: Path, suffix: str) -> Path:
    return path.with_name(f".{path.name}.{os.getpid()}-{secrets.token_hex(4)}{suffix}")


def _write_all(fd: int, data: bytes | memoryview) -> None:
    view = memoryview(data)
    while view:
        n = os.write(fd, view)
        view = view[n:]


def _disk_error(err: OSError, path: Path, what: str) -> CollectError:
    if err.errno in (errno.ENOSPC, errno.EDQUOT):
        free = shutil.disk_usage(path.parent).free  # (not _free_bytes: the truth, whatever the check said)
        return DiskFullError(f"no space left on the device of {path.parent} while writing {what} "
                             f"({free / 1e6:.1f} MB free); free some space or collect into another folder "
                             f"(out_dir=...), then rerun to resume")
    return CollectError(f"could not write {path} ({err.strerror or err}); check the folder and rerun to resume")


def write_bytes_tmp(path: Path, data: bytes, suffix: str = ".part") -> Path:
    """Write ``data`` to a new temporary name next to ``path`` (fsynced); return that name. On any
    failure the temporary file is removed and a CollectError (DiskFullError on ENOSPC) raised."""
    tmp = _tmp_name(path, suffix)
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0), 0o644)
    except OSError as err:
        raise _disk_error(err, path, path.name) from None
    try:
        try:
            _write_all(fd, data)
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError as err:
        tmp.unlink(missing_ok=True)
        raise _disk_error(err, path, path.name) from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return tmp


def write_json(path: Path, obj: Any) -> None:
    """Write JSON atomically (temporary name unique to the process, then rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = write_bytes_tmp(path, json.dumps(obj, indent=1, sort_keys=True).encode(), ".tmp")
    os.replace(tmp, path)


def cil_bytes(rgb: np.ndarray, targets: np.ndarray) -> bytes:
    """One CIL HDF5 file, built in memory (``rgb`` chunked per image, as ``cil_hdf5.write_file``)."""
    import h5py

    rgb = np.ascontiguousarray(rgb, dtype=np.uint8)
    targets = np.ascontiguousarray(targets, dtype=np.float32)
    bio = io.BytesIO()
    with h5py.File(bio, "w") as f:
        f.create_dataset("rgb", data=rgb, chunks=(1, *IMAGE_SHAPE))
        f.create_dataset("targets", data=targets)
    return bio.getvalue()


def _free_bytes(path: Path) -> int:
    return shutil.disk_usage(path).free


def check_free_space(out_dir: Path, need: int, what: str) -> None:
    free = _free_bytes(out_dir)
    if free < need:
        raise DiskFullError(f"not enough free space in {out_dir}: {what} needs ~{need / 1e6:.1f} MB, "
                            f"{free / 1e6:.1f} MB free; free some space or collect into another folder (out_dir=...)")


# ------------------------------------------------------------------------------------------------
# the lock


class FolderLock:
    """An exclusive ``flock`` on ``<folder>/.collect.lock`` that records its holder in the file."""

    def __init__(self, folder: Path, wait: float | None = 0.0, info: dict | None = None) -> None:
        self.folder, self.wait, self.info = Path(folder), wait, dict(info or {})
        self.started = time.strftime("%Y-%m-%d %H:%M:%S")
        self.path = self.folder / LOCK_NAME
        self.fd: int | None = None

    def holder(self) -> str:
        try:
            h = json.loads(self.path.read_text() or "{}")
        except (OSError, ValueError):
            h = {}
        if not h.get("pid"):
            return "a process that has not recorded itself yet"
        return f"pid {h['pid']} on {h.get('host', '?')}, started {h.get('started', '?')}" + (
            f" ({h['what']})" if h.get("what") else "")

    def acquire(self) -> "FolderLock":
        import fcntl

        try:
            self.fd = os.open(self.path, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o644)
        except OSError as err:
            raise CollectError(f"cannot write to the output folder {self.folder} ({err.strerror}); give a "
                               f"writable out_dir") from None
        t0, said = time.monotonic(), False
        while True:
            try:
                fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except OSError as err:
                if not isinstance(err, BlockingIOError):
                    os.close(self.fd)
                    self.fd = None
                    raise CollectError(f"cannot lock the output folder {self.folder} ({err.strerror}); its file "
                                       f"system does not support flock: collect into a local folder") from None
                waited = time.monotonic() - t0
                if self.wait is not None and waited >= self.wait:
                    os.close(self.fd)
                    self.fd = None
                    after = f" after waiting {waited:.0f} s" if self.wait else ""
                    raise FolderLockedError(
                        f"{self.folder} is being collected into by another process ({self.holder()}){after}; "
                        f"wait for it to finish (lock_wait=null waits), or collect into another folder") from None
                if not said:
                    log.warning("waiting for %s: another process is collecting into it (%s)", self.folder,
                                self.holder())
                    said = True
                time.sleep(0.2)
        self.update()
        return self

    def update(self, **extra: Any) -> None:
        """Record the holder (and ``extra``, e.g. worker pids) in the lock file."""
        self.info.update(extra)
        rec = {"pid": os.getpid(), "host": socket.gethostname(), "started": self.started, **self.info}
        data = json.dumps(rec).encode()
        try:
            os.ftruncate(self.fd, 0)
            os.pwrite(self.fd, data, 0)
        except OSError as err:
            self.release()
            raise _disk_error(err, self.path, "the lock file") from None

    def release(self) -> None:
        if self.fd is None:
            return
        import fcntl

        try:
            os.ftruncate(self.fd, 0)
        except OSError:
            pass
        fcntl.flock(self.fd, fcntl.LOCK_UN)
        os.close(self.fd)
        self.fd = None

    def __enter__(self) -> "FolderLock":
        return self.acquire()

    def __exit__(self, *exc: Any) -> None:
        self.release()


# ------------------------------------------------------------------------------------------------
# one episode


class _ParentGone(Exception):
    pass


def _parent_alive(parent_pid: int | None) -> bool:
    return parent_pid is None or os.getppid() == parent_pid


def _close_env(env: Any, exc: tuple) -> None:
    if hasattr(env, "__exit__"):
        env.__exit__(*exc)
    elif hasattr(env, "close"):
        env.close()


def run_episode(cfg: dict, ep: dict, out_dir: Path, backend: Any, parent_pid: int | None = None) -> dict:
    """Drive one episode and write its files; returns its marker (files, counts, route).

    ``parent_pid``: in a worker, the collector's pid; the episode is dropped if the collector is gone."""
    from cicfw.sim.expert import ExpertParams, Noiser

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
    if not _parent_alive(parent_pid):
        raise _ParentGone()
    write_json(out_dir / ".episodes" / f"{ep['id']}.json", marker)
    return marker


def write_episode_files(out_dir: Path, ep_id: str, rgb: np.ndarray, tg: np.ndarray,
                        parent_pid: int | None = None) -> list[dict]:
    """An episode's parts under temporary names, then (all written) under their final names."""
    files, parts = [], []
    try:
        for p, a in enumerate(range(0, len(tg), SAMPLES_PER_FILE)):
            name = f"{ep_id}_{p:03d}.h5"
            data = cil_bytes(rgb[a:a + SAMPLES_PER_FILE], tg[a:a + SAMPLES_PER_FILE])
            parts.append((write_bytes_tmp(out_dir / name, data), out_dir / name))
            files.append({"name": name, "samples": int(min(SAMPLES_PER_FILE, len(tg) - a)), "bytes": len(data),
                          "sha256": hashlib.sha256(data).hexdigest()})
        if not _parent_alive(parent_pid):
            raise _ParentGone()
    except BaseException:
        for tmp, _ in parts:
            tmp.unlink(missing_ok=True)
        raise
    for tmp, final in parts:
        os.replace(tmp, final)
    return files


# ------------------------------------------------------------------------------------------------
# workers


def _die_with_parent(parent_pid: int) -> None:
    """SIGKILL this process when ``parent_pid`` dies: the kernel's PR_SET_PDEATHSIG on Linux, and a
    thread that polls the parent pid every second everywhere."""
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(1, int(signal.SIGKILL), 0, 0, 0)  # PR_SET_PDEATHSIG = 1
        except (OSError, AttributeError):
            pass
    if os.getppid() != parent_pid:  # the parent died before prctl
        os._exit(1)

    def watch() -> None:
        while True:
            time.sleep(1.0)
            if os.getppid() != parent_pid:
                os._exit(1)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def _worker_main(index: int, sim: dict, cfg: dict, out_dir: str, parent_pid: int, tasks: Any, results: Any) -> None:
    _die_with_parent(parent_pid)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C and ends its workers
    try:
        backend = make_backend(sim)
    except BaseException as err:
        results.put(("error", index, None, _portable(err), traceback.format_exc()))
        return
    try:
        while True:
            ep = tasks.get()
            if ep is None:
                return
            results.put(("start", index, ep["id"]))
            try:
                marker = run_episode(cfg, ep, Path(out_dir), backend, parent_pid=parent_pid)
            except _ParentGone:
                os._exit(1)
            except BaseException as err:
                results.put(("error", index, ep["id"], _portable(err), traceback.format_exc()))
                return
            results.put(("done", index, marker))
    finally:
        _close_backend(backend)


def _portable(err: BaseException) -> BaseException | None:
    """``err`` if it survives pickling (so the parent can raise the same user error), else None."""
    import pickle

    try:
        pickle.loads(pickle.dumps(err))
        return err
    except Exception:
        return None


def _run_workers(cfg: dict, todo: list[dict], out_dir: Path, n: int, on_marker: Callable[[dict], None],
                 lock: FolderLock) -> None:
    ctx = get_context("spawn")
    tasks, results = ctx.Queue(), ctx.Queue()
    sim = dict(cfg["sim"])
    name = sim.get("name", "embedded")
    per_worker = getattr(SIM_BACKENDS.get(name), "worker_kwargs", None)
    specs = []
    for i in range(n):
        kw = {k: v for k, v in sim.items() if k != "name"}
        if per_worker is not None:
            kw = per_worker(kw, i)
            if kw is None:
                break
        specs.append({"name": name, **kw})
    for ep in todo:
        tasks.put(ep)
    for _ in specs:
        tasks.put(None)
    procs = [ctx.Process(target=_worker_main, args=(i, s, cfg, str(out_dir), os.getpid(), tasks, results),
                         name=f"cicfw-collect-{i}", daemon=True) for i, s in enumerate(specs)]
    current: dict[int, str | None] = {}
    try:
        for p in procs:
            p.start()
        lock.update(workers=[p.pid for p in procs])
        left = len(todo)
        while left:
            try:
                msg = results.get(timeout=0.5)
            except queue.Empty:
                for i, p in enumerate(procs):
                    if p.exitcode not in (None, 0):
                        raise CollectError(f"collect worker {i} (pid {p.pid}) died with exit code {p.exitcode} "
                                           f"while collecting episode {current.get(i)}; rerun to resume")
                if all(p.exitcode is not None for p in procs):
                    raise CollectError(f"every collect worker has exited with {left} episode(s) left; rerun to resume")
                continue
            kind, i = msg[0], msg[1]
            if kind == "start":
                current[i] = msg[2]
            elif kind == "done":
                current[i] = None
                left -= 1
                on_marker(msg[2])
            else:
                _, _, ep_id, err, tb = msg
                if isinstance(err, ValueError):  # a user error (CollectError, TownError ...): the same one line
                    raise err
                where = f" on episode {ep_id}" if ep_id else ""
                raise RuntimeError(f"collect worker {i} failed{where}:\n{tb}")
    finally:
        for p in procs:
            if p.is_alive():
                p.terminate()
        for p in procs:
            p.join(5.0)
            if p.is_alive():
                p.kill()
                p.join(5.0)
        tasks.cancel_join_thread()
        results.cancel_join_thread()


# ------------------------------------------------------------------------------------------------
# the dataset


def clean_partials(out_dir: Path) -> int:
    """Remove what a killed run left half-written (temporary names only; finished files stay). Only
    ever called while holding the folder's lock, so no live writer owns them."""
    n = 0
    for p in (list(out_dir.glob(".*.part")) + list(out_dir.glob(".*.tmp"))
              + list(out_dir.glob(".episodes/.*"))):
        if p.is_file():
            p.unlink(missing_ok=True)
            n += 1
    return n


def file_sha256(path: Path) -> str:
    """The SHA-256 of a file's bytes, read in 8 MB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(8 << 20):
            h.update(block)
    return h.hexdigest()


def file_problem(out_dir: Path, f: dict) -> tuple[str, str] | None:
    """What is wrong with one recorded file of a marker, as (kind, one-line reason), or None when it is
    sound: ``missing``; ``corrupt`` (another size, another SHA-256, or, without a recorded checksum, not a
    CIL file with the recorded number of samples)."""
    p = out_dir / f["name"]
    try:
        size = p.stat().st_size
    except FileNotFoundError:
        return "missing", "no such file"
    except OSError as err:
        return "missing", f"cannot read it ({err.strerror or err})"
    if "bytes" in f and size != f["bytes"]:
        return "corrupt", f"{size} bytes, {f['bytes']} when it was written (truncated or overwritten)"
    try:
        if "sha256" in f:
            now = file_sha256(p)
            if now != f["sha256"]:
                return "corrupt", (f"its bytes no longer match the checksum recorded when it was written "
                                   f"(sha256 {now[:16]}..., recorded {f['sha256'][:16]}...)")
            return None
        n = check_file(p).n
    except CILFormatError as err:
        return "corrupt", str(err).removeprefix(f"{p}: ")
    except OSError as err:
        return "missing", f"cannot read it ({err.strerror or err})"
    if n != f["samples"]:
        return "corrupt", f"{n} samples, {f['samples']} when it was written"
    return None


def _marker_problems(out_dir: Path, m: dict) -> list[tuple[str, str, str]]:
    """(file name, kind, reason) for every file of the marker that is not sound; a marker without files
    is a problem of its own."""
    if not m.get("files"):
        return [(f"{m.get('id', '?')} (no files recorded)", "corrupt", "its marker records no file")]
    out = []
    for f in m["files"]:
        problem = file_problem(out_dir, f)
        if problem is not None:
            out.append((f["name"], *problem))
    return out


def _read_markers(out_dir: Path, plan: list[dict], chash: str, say: bool = False) -> dict[str, dict]:
    """The markers of planned episodes whose files are all sound. ``say``: a warning per unsound file of a
    finished episode (its episode is collected again)."""
    markers = {}
    for ep in plan:
        mp = out_dir / ".episodes" / f"{ep['id']}.json"
        try:
            m = json.loads(mp.read_text())
        except (OSError, ValueError):
            continue
        if m.get("config_hash", chash) != chash or m.get("seed") != ep["seed"]:
            continue
        problems = _marker_problems(out_dir, m)
        if not problems:
            markers[ep["id"]] = m
        elif say:
            for name, kind, why in problems:
                log.warning("%s: %s: %s; episode %s is collected again", out_dir / name, kind, why, ep["id"])
    return markers


def _record_checksums(out_dir: Path, markers: dict[str, dict]) -> int:
    """Record the SHA-256 of files of markers written before checksums were kept (those files have just
    been checked for size and layout); returns how many files got one."""
    n = 0
    for ep_id, m in markers.items():
        legacy = [f for f in m["files"] if "sha256" not in f]
        if not legacy:
            continue
        for f in legacy:
            f["sha256"] = file_sha256(out_dir / f["name"])
        write_json(out_dir / ".episodes" / f"{ep_id}.json", m)
        n += len(legacy)
    if n:
        log.info("recorded the checksums of %d file(s) of %s collected before cicfw kept checksums (until now "
                 "they could be checked for size and layout only)", n, out_dir)
    return n


def _remove_episodes(out_dir: Path, eps: list[dict]) -> None:
    ids = {ep["id"] for ep in eps}
    for ep_id in ids:
        (out_dir / ".episodes" / f"{ep_id}.json").unlink(missing_ok=True)
    for p in out_dir.glob("*.h5"):
        if p.name.rsplit("_", 1)[0] in ids:
            p.unlink()


def _foreign_files(out_dir: Path, plan: list[dict]) -> list[Path]:
    ids = tuple(ep["id"] + "_" for ep in plan)
    return [p for p in sorted(out_dir.rglob("*.h5")) + sorted(out_dir.rglob("*.hdf5"))
            if p.parent != out_dir or not p.name.startswith(ids)]


def _metadata(cfg: dict, out_dir: Path, plan: list[dict], markers: dict, started: float, sim_version: str,
              complete: bool) -> dict:
    counts = {"episodes": len(markers), "samples": sum(m["samples"] for m in markers.values()),
              "steps": sum(m["steps"] for m in markers.values()),
              "files": sum(len(m["files"]) for m in markers.values()),
              "noisy_steps": sum(m["noisy_steps"] for m in markers.values())}
    cmd = {c: sum(m["commands"][c] for m in markers.values()) for c in ("2", "3", "4", "5")}
    return {
        "format": "CIL HDF5 (CoRL-2017 layout), written by cicfw.collect",
        "complete": complete, "planned_episodes": len(plan),
        "cicfw_version": __version__, "sim": cfg["sim"].get("name", "embedded"), "sim_version": sim_version,
        "config_hash": cfg["_hash"], "config": {k: v for k, v in cfg.items() if k != "_hash"},
        "towns": cfg["towns"], "weathers": cfg["weathers"], "seed": cfg["seed"],
        "cameras": {c: {"id": CAMERA_IDS[c][0], "yaw_deg": CAMERA_IDS[c][1]} for c in cfg["cameras"]},
        "counts": counts, "step_commands": cmd,
        "units": {"speed": "km/h", "position": "m (rear axle)", "time": "ms of game time",
                  "steer": "[-1, 1], positive right; targets[5] = steering applied (expert + noise)"},
        "episodes": {k: {x: m[x] for x in ("town", "weather", "seed", "samples", "noisy_episode",
                                            "noisy_steps", "route_length_m", "distance_driven_m", "commands")}
                     for k, m in sorted(markers.items())},
        "files": {f["name"]: {"episode": k, "samples": f["samples"], **({"sha256": f["sha256"]} if "sha256" in f else {})}
                  for k, m in sorted(markers.items()) for f in m["files"]},
        "collection_seconds": round(time.time() - started, 1),
    }


def _prepare_folder(out_dir: Path) -> None:
    try:
        if out_dir.exists() and not out_dir.is_dir():
            raise CollectError(f"out_dir {out_dir} is a file, not a folder; give a folder")
        out_dir.mkdir(parents=True, exist_ok=True)
    except CollectError:
        raise
    except OSError as err:
        raise CollectError(f"cannot create the output folder {out_dir} ({err.strerror}); give a writable "
                           f"out_dir") from None
    if not os.access(out_dir, os.W_OK | os.X_OK):
        raise CollectError(f"cannot write to the output folder {out_dir} (permission denied); give a writable out_dir")


def collect_dataset(cfg_collect: Any, out_dir: str | Path, progress: bool = True) -> Path:
    """Collect (or finish collecting) a dataset into ``out_dir``; returns the metadata JSON path.

    ``cfg_collect``: a dict / DictConfig with any of DEFAULTS' keys (missing ones take the default;
    ``sim`` is the backend's config node). A rerun with the same config skips finished episodes; a
    different config in a folder that holds a dataset is an error (use another folder)."""
    raw = _plain(cfg_collect)
    backend = make_backend(_sim_node(raw))
    try:
        return _collect(raw, backend, Path(out_dir), progress)
    finally:
        _close_backend(backend)


def _collect(raw: dict, backend: Any, out_dir: Path, progress: bool) -> Path:
    cfg = resolve_config(raw, backend)
    sim_version = SIM_VERSION if cfg["sim"].get("name", "embedded") == "embedded" else str(
        getattr(backend, "data_version", cfg["sim"].get("name")))
    cfg["_hash"] = chash = config_hash(cfg)
    out_dir = out_dir.expanduser().resolve()
    _prepare_folder(out_dir)
    what = f"cicfw collect, seed {cfg['seed']}, {cfg['episodes']} episode(s), config {chash}"
    with FolderLock(out_dir, cfg["lock_wait"], {"what": what}) as lock:
        clean_partials(out_dir)
        meta_path = out_dir / META_NAME
        old = None
        if meta_path.exists():
            try:
                old = json.loads(meta_path.read_text())
            except ValueError:
                raise CollectError(f"{meta_path} is not valid JSON; delete the folder or collect into "
                                   f"another one") from None
            if old.get("config_hash") != chash:
                raise CollectConfigError(
                    f"{out_dir} holds a dataset collected with another config (hash {old.get('config_hash')} "
                    f"!= {chash}, seed {old.get('seed')}); collect into another folder or delete this one")
        plan = episode_plan(cfg)
        foreign = _foreign_files(out_dir, plan)
        if foreign:
            raise CollectError(f"{out_dir} holds {len(foreign)} HDF5 file(s) this collection does not write "
                               f"(e.g. {foreign[0].relative_to(out_dir)}); collect into an empty folder")
        markers = _read_markers(out_dir, plan, chash, say=True)
        _record_checksums(out_dir, markers)
        todo = [ep for ep in plan if ep["id"] not in markers]
        started = time.time()
        if not todo:
            meta = _metadata(cfg, out_dir, plan, markers, started, old.get("sim_version", sim_version)
                             if old else sim_version, True)
            if old is None or not old.get("complete"):
                write_json(meta_path, meta)
            elif old.get("files") != meta["files"]:  # checksums just recorded: the rest stays as collected
                write_json(meta_path, {**old, "files": meta["files"]})
            return meta_path
        if old is not None and old.get("sim_version", sim_version) != sim_version:
            raise CollectError(f"{out_dir} holds an unfinished dataset of simulator {old.get('sim_version')}; "
                               f"this is {sim_version}, and finishing it would mix the two: delete the folder or "
                               f"collect into another one")
        _remove_episodes(out_dir, todo)  # what is left of them did not validate; they are collected again
        check_free_space(out_dir, len(todo) * episode_bytes(cfg), f"the {len(todo)} episode(s) left")
        write_json(meta_path, _metadata(cfg, out_dir, plan, markers, started, sim_version, False))
        log.info("collecting %d episode(s) (%d already done) into %s", len(todo), len(markers), out_dir)
        bar = _Progress(progress, len(todo) * steps_per_episode(cfg) * len(cfg["cameras"]),
                        f"collect {out_dir.name}")

        def on_marker(m: dict) -> None:
            markers[m["id"]] = m
            write_json(meta_path, _metadata(cfg, out_dir, plan, markers, started, sim_version, False))
            bar.advance(m["samples"])

        workers = min(int(cfg["workers"]), len(todo))
        try:
            if workers <= 1:
                for ep in todo:
                    on_marker(run_episode(cfg, ep, out_dir, backend))
            else:
                _close_backend(backend)  # each worker builds its own (one simulator server each)
                _run_workers(cfg, todo, out_dir, workers, on_marker, lock)
        finally:
            bar.close()
            clean_partials(out_dir)  # what an interrupted episode or a killed worker left
        markers = _read_markers(out_dir, plan, chash)
        done = len(markers) == len(plan)
        write_json(meta_path, _metadata(cfg, out_dir, plan, markers, started, sim_version, done))
        if not done:
            missing = sorted(set(ep["id"] for ep in plan) - set(markers))
            raise CollectError(f"{len(missing)} episode(s) of {out_dir} did not validate after collection "
                               f"(e.g. {missing[0]}); rerun to collect them again")
        return meta_path


class VerifyReport:
    """What ``verify_dataset`` found: ``problems`` as (path, kind, reason), kind one of ``missing``,
    ``corrupt``, ``unfinished`` (a file of an episode without a marker: a rerun removes it)."""

    def __init__(self, out_dir: Path) -> None:
        self.out_dir = out_dir
        self.files = self.bytes = self.unchecked = self.episodes = self.planned = 0
        self.complete = False
        self.problems: list[tuple[Path, str, str]] = []

    def lines(self) -> list[str]:
        """One line per file that is not sound."""
        return [f"{kind}: {path}: {why}" for path, kind, why in self.problems]

    @property
    def ok(self) -> bool:
        return not self.problems and self.complete

    def summary(self) -> str:
        if self.problems:
            return (f"{len(self.problems)} of {self.files} file(s) of {self.out_dir} are missing, corrupt or "
                    f"unfinished (listed above); rerun the same collect command (without verify) to collect "
                    f"their episodes again")
        if not self.complete:
            return (f"{self.out_dir} is an unfinished dataset ({self.episodes} of {self.planned} episode(s) "
                    f"finished; the files of those are sound); rerun the same collect command to finish it")
        legacy = (f"; {self.unchecked} collected before cicfw kept checksums were checked for size and layout "
                  f"only (a rerun of collect records their checksums)" if self.unchecked else "")
        return (f"verified {self.out_dir}: {self.episodes} episode(s), {self.files} file(s) ({self.bytes / 1e6:.1f} MB), "
                f"all match their checksums{legacy}")


def verify_dataset(out_dir: str | Path, lock_wait: float | None = 0.0) -> VerifyReport:
    """Check every file of a collected dataset against its recorded size and SHA-256 (files without a
    recorded checksum: size and CIL layout), changing nothing. Holds the folder's lock while it reads (a
    collection in progress is waited for as ``lock_wait`` says), unless the folder is read-only (then no
    one can be writing into it). A folder without ``dataset_metadata.json`` is a CollectError."""
    out_dir = Path(out_dir).expanduser().resolve()
    meta_path = out_dir / META_NAME
    if not meta_path.is_file():
        what = "does not exist" if not out_dir.exists() else f"has no {META_NAME} (cicfw collect writes one)"
        raise CollectError(f"no dataset to verify in {out_dir}: it {what}; give the out_dir of a collection "
                           f"(out_dir=...)")
    lock = None
    if os.access(out_dir, os.W_OK | os.X_OK):
        lock = FolderLock(out_dir, lock_wait, {"what": "cicfw collect verify=true"}).acquire()
    try:
        try:
            meta = json.loads(meta_path.read_text())
        except ValueError:
            raise CollectError(f"{meta_path} is not valid JSON; this folder's dataset cannot be verified: "
                               f"delete it and collect again") from None
        rep = VerifyReport(out_dir)
        rep.planned = int(meta.get("planned_episodes", 0))
        recorded: set[str] = set()
        for mp in sorted((out_dir / ".episodes").glob("*.json")):
            try:
                m = json.loads(mp.read_text())
            except (OSError, ValueError):
                continue  # an unreadable marker: its episode counts as unfinished
            if m.get("config_hash", meta.get("config_hash")) != meta.get("config_hash"):
                continue
            rep.episodes += 1
            problems = {name: (kind, why) for name, kind, why in _marker_problems(out_dir, m)}
            for f in m.get("files", []):
                recorded.add(f["name"])
                rep.files += 1
                rep.bytes += int(f.get("bytes", 0))
                rep.unchecked += "sha256" not in f
                if f["name"] in problems:
                    rep.problems.append((out_dir / f["name"], *problems.pop(f["name"])))
            rep.problems += [(out_dir / name, kind, why) for name, (kind, why) in problems.items()]
        for p in sorted(out_dir.glob("*.h5")):
            if p.name not in recorded:
                rep.files += 1
                rep.problems.append((p, "unfinished", "no finished episode records it (a collection stopped "
                                                      "before its episode's marker was written)"))
        rep.complete = bool(meta.get("complete")) and rep.episodes >= rep.planned
        return rep
    finally:
        if lock is not None:
            lock.release()


class _Progress:
    """A rich progress bar in samples (silent when disabled)."""

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
