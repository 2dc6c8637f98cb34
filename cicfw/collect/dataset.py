"""A dataset into a folder: locked, planned, resumed where finished episodes are sound, collected in this
process or in workers, its metadata kept current."""
from __future__ import annotations

import json
import logging
import os
import time
from pathlib import Path
from typing import Any, Callable

from cicfw.collect.config import (close_backend, config_hash, episode_bytes, episode_plan, make_backend, plain_config,
                                  resolve_config, sim_node, steps_per_episode)
from cicfw.collect.episode import run_episode
from cicfw.collect.errors import CollectConfigError, CollectError
from cicfw.collect.integrity import foreign_files, read_markers, record_checksums
from cicfw.collect.lock import FolderLock
from cicfw.collect.metadata import META_NAME, SIM_VERSION, dataset_metadata, planned_sets
from cicfw.collect.workers import run_workers
from cicfw.collect.writing import check_free_space, write_json
from cicfw.core.files import temp_name_bytes
from cicfw.core.progress import ProgressBar
from cicfw.core.run_folder import name_max
from cicfw.core.spawning import check_spawn_safe

log = logging.getLogger(__name__)


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


def _remove_episodes(out_dir: Path, eps: list[dict]) -> None:
    ids = {ep["id"] for ep in eps}
    for ep_id in ids:
        (out_dir / ".episodes" / f"{ep_id}.json").unlink(missing_ok=True)
    for p in out_dir.glob("*.h5"):
        if p.name.rsplit("_", 1)[0] in ids:
            p.unlink()


def _refuse_foreign_files(out_dir: Path, plan: list[dict], chash: str) -> None:
    """Refuse a folder that holds HDF5 files this collection did not write: never mix in, nor overwrite, the
    user's own."""
    foreign = foreign_files(out_dir, plan, chash)
    if foreign:
        names = ", ".join(str(p.relative_to(out_dir)) for p in foreign[:3]) + (", ..." if len(foreign) > 3 else "")
        unrecorded = "" if (out_dir / META_NAME).exists() else f", recorded in no {META_NAME} of it"
        raise CollectError(f"{out_dir} holds {len(foreign)} HDF5 file(s) this collection did not write{unrecorded} "
                           f"({names}); collect into an empty folder", key="out_dir", value=out_dir)


def _refuse_inside_a_dataset(out_dir: Path) -> None:
    """A folder inside another collection's: data folders are read recursively, so these episodes would join
    that dataset for everyone who trains on it, unlisted in its metadata."""
    for parent in out_dir.parents:
        if (parent / META_NAME).is_file():
            raise CollectConfigError(f"out_dir {out_dir} is inside the collected dataset {parent}, whose readers "
                                     f"take every HDF5 file below it: these episodes would join that dataset; "
                                     f"collect into a folder outside it", key="out_dir", value=out_dir)


def _prepare_folder(out_dir: Path) -> None:
    try:
        if out_dir.exists() and not out_dir.is_dir():
            raise CollectError(f"out_dir {out_dir} is a file, not a folder; give a folder", key="out_dir",
                               value=out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
    except CollectError:
        raise
    except OSError as err:
        raise CollectError(f"cannot create the output folder {out_dir} ({err.strerror}); give a writable "
                           f"out_dir", key="out_dir", value=out_dir) from None
    if not os.access(out_dir, os.W_OK | os.X_OK):
        raise CollectError(f"cannot write to the output folder {out_dir} (permission denied); give a writable out_dir",
                           key="out_dir", value=out_dir)


def _say_what_the_plan_leaves_out(cfg: dict, plan: list[dict]) -> None:
    """One warning naming the listed towns and weathers that get no episode (fewer episodes than town x weather
    pairs): the dataset does not hold them, and its metadata does not list them."""
    towns, weathers = planned_sets(cfg, plan)
    left = [t for t in cfg["towns"] if t not in towns] + [w for w in cfg["weathers"] if w not in weathers]
    if left:
        log.warning("episodes=%d go round-robin over the %d town x weather pairs, town by town: the dataset holds "
                    "no episode of %s; give episodes >= %d to collect every pair",
                    cfg["episodes"], len(cfg["towns"]) * len(cfg["weathers"]), ", ".join(map(str, left)),
                    len(cfg["towns"]) * len(cfg["weathers"]))


def collect_dataset(cfg_collect: Any, out_dir: str | Path, progress: bool = True,
                    on_start: Callable[[], None] | None = None) -> Path:
    """Collect (or finish collecting) a dataset into ``out_dir``; returns the metadata JSON path.

    ``cfg_collect``: a dict / DictConfig with any of DEFAULTS' keys (missing ones take the default;
    ``sim`` is the backend's config node). A rerun with the same config skips finished episodes; a
    different config in a folder that holds a dataset is an error (use another folder). ``on_start`` is
    called once every check has passed, as the first episode is about to be collected."""
    raw = plain_config(cfg_collect)
    backend = make_backend(sim_node(raw))
    try:
        return _collect(raw, backend, Path(out_dir), progress, on_start)
    finally:
        close_backend(backend)


def _collect(raw: dict, backend: Any, out_dir: Path, progress: bool, on_start: Callable[[], None] | None) -> Path:
    cfg = resolve_config(raw, backend)
    sim_version = SIM_VERSION if cfg["sim"].get("name", "embedded") == "embedded" else str(
        getattr(backend, "data_version", cfg["sim"].get("name")))
    cfg["_hash"] = chash = config_hash(cfg)
    out_dir = out_dir.expanduser().resolve()
    if int(cfg["workers"]) > 1:  # before the folder's lock, on which a worker running the script over would wait
        check_spawn_safe("collect_dataset", "collect.workers", cfg["workers"])
    _refuse_inside_a_dataset(out_dir)
    # an episode's longest file name is its HDF5 part's temporary one (cicfw.core.files): a town file's long
    # stem must be refused now, not after the episode is driven. A worker writes it, whose pid may have more
    # digits than this process's: counted as the widest (7, Linux's largest pid)
    longest = max(episode_plan(cfg), key=lambda ep: len(os.fsencode(ep["id"])))
    size, limit = temp_name_bytes(f"{longest['id']}_000.h5", ".part", pid=9_999_999), name_max(out_dir)
    if size > limit:
        raise CollectConfigError(f"collect.towns: the town {longest['town']!r} makes episode file names of {size} "
                                 f"bytes (while written), more than this filesystem allows ({limit}); give the town "
                                 f"file a shorter name", key="collect.towns", value=longest["town"])
    _prepare_folder(out_dir)
    if not (out_dir / META_NAME).exists():  # not a collection's folder: refuse it before the lock file is made
        _refuse_foreign_files(out_dir, episode_plan(cfg), chash)
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
                    f"!= {chash}, seed {old.get('seed')}); collect into another folder or delete this one",
                    key="out_dir", value=out_dir)
        plan = episode_plan(cfg)
        _say_what_the_plan_leaves_out(cfg, plan)
        _refuse_foreign_files(out_dir, plan, chash)  # again under the lock: a collection's folder, or one changed since
        markers = read_markers(out_dir, plan, chash, say=True)
        record_checksums(out_dir, markers)
        todo = [ep for ep in plan if ep["id"] not in markers]
        started = time.time()
        if not todo:
            meta = dataset_metadata(cfg, out_dir, plan, markers, started,
                                    old.get("sim_version", sim_version) if old else sim_version, True)
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
        if on_start is not None:
            on_start()
        write_json(meta_path, dataset_metadata(cfg, out_dir, plan, markers, started, sim_version, False))
        log.info("collecting %d episode(s) (%d already done) into %s", len(todo), len(markers), out_dir)
        bar = ProgressBar(progress, len(todo) * steps_per_episode(cfg) * len(cfg["cameras"]),
                          f"collect {out_dir.name}", "samples")

        def on_marker(m: dict) -> None:
            markers[m["id"]] = m
            write_json(meta_path, dataset_metadata(cfg, out_dir, plan, markers, started, sim_version, False))
            bar.advance(m["samples"])

        workers = min(int(cfg["workers"]), len(todo))
        try:
            if workers <= 1:
                for ep in todo:
                    on_marker(run_episode(cfg, ep, out_dir, backend))
            else:
                close_backend(backend)  # each worker builds its own (one simulator server each)
                run_workers(cfg, todo, out_dir, workers, on_marker, lock)
        finally:
            bar.close()
            clean_partials(out_dir)  # what an interrupted episode or a killed worker left
        markers = read_markers(out_dir, plan, chash)
        done = len(markers) == len(plan)
        write_json(meta_path, dataset_metadata(cfg, out_dir, plan, markers, started, sim_version, done))
        if not done:
            missing = sorted(set(ep["id"] for ep in plan) - set(markers))
            raise CollectError(f"{len(missing)} episode(s) of {out_dir} did not validate after collection "
                               f"(e.g. {missing[0]}); rerun to collect them again")
        return meta_path
