"""The collection stage: a CIL HDF5 dataset from any simulator backend (``SIM_BACKENDS``).

``collect_dataset(cfg, out_dir)`` drives random multi-junction routes (turns drawn to keep left / right /
straight balanced) in the chosen towns and weathers with the expert and CIL's steering noise; each step
writes one sample per camera. Files: ``<episode>_<part>.h5`` (200 samples each, the last part of an
episode may be shorter), one JSON marker per finished episode under ``.episodes/``, and
``dataset_metadata.json`` (towns, weathers, seeds, sim version, counts, file -> episode). The app
``python -m cicfw.collect`` (``app``) is a thin shell around this package; ``schema`` is its config's
schema: conf/collect.yaml puts its ``schema`` package on Hydra's search path (``pkg://cicfw.collect.schema``), and
importing that registers the schema in Hydra's ConfigStore before a collect config is composed.

The package sits above the simulator (``cicfw.sim``) and the data layer (``cicfw.data``, whose CIL format it
writes) and only apps import it. Its modules (one job each) and what the collector guarantees (each with a
fault test in ``tests/test_collect_integrity.py``) are in docs/simulator.md, "Collecting data".

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

from cicfw.collect.config import (CAMERA_IDS, DEFAULTS, config_hash, episode_bytes, episode_plan, make_backend,
                                  resolve_config, steps_per_episode, town_key)
from cicfw.collect.dataset import collect_dataset
from cicfw.collect.episode import run_episode
from cicfw.collect.errors import CollectConfigError, CollectError, DiskFullError, FolderLockedError
from cicfw.collect.integrity import VerifyReport, verify_dataset
from cicfw.collect.lock import LOCK_NAME, FolderLock
from cicfw.collect.metadata import META_NAME, SIM_VERSION

__all__ = [
    "CAMERA_IDS", "DEFAULTS", "LOCK_NAME", "META_NAME", "SIM_VERSION", "CollectConfigError", "CollectError",
    "DiskFullError", "FolderLock", "FolderLockedError", "VerifyReport", "collect_dataset", "config_hash",
    "episode_bytes", "episode_plan", "make_backend", "resolve_config", "run_episode", "steps_per_episode",
    "town_key", "verify_dataset",
]
