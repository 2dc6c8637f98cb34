"""The episode log of an evaluation run folder: finished episodes are kept as they finish.

``<run>/episodes.jsonl`` holds a header line (the run's *fingerprint*: everything that decides an
episode's result) and then one line per finished episode: its report row and its trajectory
(each channel's dtype, shape and base64 bytes). Each line is written with one ``write`` on a file opened for appending, then
flushed and fsynced, so a killed run loses at most the episode being written; a torn last line is
dropped (and cut off) when the log is opened again. A run folder is locked for the whole run
(``.evaluate.lock``, the project's ``FolderLock``; removed when the run ends) so two evaluations never
append to one log.

``EpisodeLog.open(run_dir, fingerprint)`` returns the log with the episodes already finished, or
refuses (one line) when they were driven with another fingerprint.
"""
from __future__ import annotations

import base64
import json
import os
import sys
from pathlib import Path
from typing import Any, Mapping

import numpy as np
from omegaconf import OmegaConf

from cicfw.core.files import unshare, write_all
from cicfw.core.locks import FolderBusy, FolderLock
from cicfw.core.run_folder import (EPISODE_LOG, EPISODE_LOG_FORMAT, LockedRunFolderCheck, RunFolderError,
                                   check_name_lengths, keep_held_lock, take_held_lock)

LOG_NAME = EPISODE_LOG  # its header's format makes a folder an evaluation's (``folder_owner``)
LOCK_NAME = ".evaluate.lock"
FORMAT = EPISODE_LOG_FORMAT


def _encode_traj(traj: Mapping[str, np.ndarray]) -> dict[str, list]:
    """channel -> [dtype, shape, base64 of the raw bytes]: exact, and cheap next to compressing."""
    out = {}
    for k, v in traj.items():
        a = np.ascontiguousarray(v)
        out[k] = [a.dtype.str, list(a.shape), base64.b64encode(a.tobytes()).decode("ascii")]
    return out


def _decode_traj(enc: Mapping[str, list]) -> dict[str, np.ndarray]:
    return {k: np.frombuffer(base64.b64decode(data), dtype=np.dtype(dt)).reshape(shape).copy()
            for k, (dt, shape, data) in enc.items()}


def _first_difference(old: Any, new: Any, where: str = "") -> tuple[str, Any, Any] | None:
    """The first key (dotted) whose value differs between two fingerprints, with both values."""
    if isinstance(old, Mapping) and isinstance(new, Mapping):
        for k in list(old) + [k for k in new if k not in old]:
            d = _first_difference(old.get(k), new.get(k), f"{where}.{k}" if where else str(k))
            if d is not None:
                return d
        return None
    return None if old == new else (where, old, new)


def read_log(run_dir: str | Path, trajectories: bool = True
             ) -> tuple[dict[str, Any] | None, dict[int, dict], dict[str, dict], int]:
    """(header, rows by episode index, trajectories by episode key, bytes of valid lines) of a run's
    log; a missing log reads as (None, {}, {}, 0). Undecodable lines (a torn last line) are skipped.
    ``trajectories=False`` skips decoding them (the rows alone)."""
    path = Path(run_dir) / LOG_NAME
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return None, {}, {}, 0
    header, rows, trajs, good = None, {}, {}, 0
    pos = 0
    while pos < len(data):
        end = data.find(b"\n", pos)
        if end < 0:  # torn last line: the run was killed while writing it
            break
        line = data[pos:end]
        pos = end + 1
        try:
            rec = json.loads(line)
        except (json.JSONDecodeError, UnicodeDecodeError):
            continue
        if not isinstance(rec, dict):
            continue
        if rec.get("format") == FORMAT and header is None:
            header = rec
        elif "row" in rec and "traj" in rec and header is not None:
            try:
                row = rec["row"]
                traj = _decode_traj(rec["traj"]) if trajectories else None
                if int(row["episode"]) in rows:
                    continue
                rows[int(row["episode"])] = row
                if traj is not None:
                    trajs[str(row["key"])] = traj
            except Exception:  # a damaged line: that episode is driven again
                continue
        good = pos
    return header, rows, trajs, good


class EpisodeLog:
    """The open, locked episode log of one run folder (use ``EpisodeLog.open``; close when done)."""

    def __init__(self, run_dir: Path, header: dict, rows: dict[int, dict], trajs: dict[str, dict],
                 lock: FolderLock) -> None:
        self.run_dir, self.header = run_dir, header
        self.rows, self.trajectories = rows, trajs  # episodes finished so far (earlier attempts + this one)
        self.reused = len(rows)  # finished before this attempt
        self._lock = lock
        self._fd = os.open(run_dir / LOG_NAME, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)

    @classmethod
    def open(cls, run_dir: str | Path, fingerprint: Mapping[str, Any], info: Mapping[str, Any] | None = None,
             hint: str = "") -> "EpisodeLog":
        """Lock ``run_dir`` and open its log: the finished episodes of an earlier attempt with the same
        ``fingerprint`` are kept; another fingerprint raises ``RunFolderError`` naming the first
        difference (``hint`` says how to start a new folder). ``info`` is stored for people (e.g. the
        checkpoint's path) but not compared."""
        run_dir = Path(run_dir)
        run_dir.mkdir(parents=True, exist_ok=True)
        fp = json.loads(json.dumps(fingerprint))  # as it reads back from the file
        held = take_held_lock(run_dir / LOCK_NAME)  # taken by EvaluateRunFolderCheck before Hydra wrote here
        lock = held or RunFolderLock(run_dir).acquire()
        try:
            header, rows, trajs, good = read_log(run_dir)
            if header is not None and header.get("fingerprint") != fp:
                what, old, new = _first_difference(header.get("fingerprint") or {}, fp) or ("fingerprint", "?", "?")
                raise RunFolderError(
                    f"{str(run_dir)!r} holds {len(rows)} episode(s) of another evaluation ({what}: "
                    f"{_short(old)} there, {_short(new)} now), so it cannot resume there; {hint or 'give a new output folder'}",
                    key=what, value=new)
            if header is None:
                _check_no_foreign_report(run_dir, fp, hint)
                rows, trajs = {}, {}
                header = {"format": FORMAT, "fingerprint": fp, "info": dict(info or {})}
                with open(run_dir / LOG_NAME, "wb") as f:  # a new log (or one torn before its header)
                    f.write((json.dumps(header) + "\n").encode())
                    f.flush()
                    os.fsync(f.fileno())
            else:
                unshare(run_dir / LOG_NAME)  # a hard-linked copy of another folder's log (cp -al): one of its own
                if good < (run_dir / LOG_NAME).stat().st_size:
                    os.truncate(run_dir / LOG_NAME, good)  # cut a torn last line before appending
            return cls(run_dir, header, rows, trajs, lock)
        except BaseException:
            if held is not None:  # the app puts the folder back under it, then lets go (release_folder_locks)
                keep_held_lock(held)
            else:
                lock.release()
            raise

    def add(self, row: Mapping[str, Any], traj: Mapping[str, np.ndarray]) -> None:
        """Keep one finished episode: one line, written at once, flushed to the disk."""
        rec = {"row": dict(row), "traj": _encode_traj(traj)}
        data = (json.dumps(rec) + "\n").encode()
        write_all(self._fd, data)  # a full disk's short write: the next write raises its OSError (ENOSPC)
        os.fsync(self._fd)
        self.rows[int(row["episode"])] = dict(row)
        self.trajectories[str(row["key"])] = {k: np.asarray(v) for k, v in traj.items()}

    def close(self) -> None:
        if self._fd is not None:
            try:
                os.close(self._fd)
            except OSError:
                pass
            self._fd = None
        self._lock.release()

    def __enter__(self) -> "EpisodeLog":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def _short(v: Any) -> str:
    s = json.dumps(v) if not isinstance(v, str) else repr(v)
    return s if len(s) <= 80 else s[:77] + "..."


def _check_no_foreign_report(run_dir: Path, fp: Mapping[str, Any], hint: str) -> None:
    """A folder with a report but no log (written by an older cicfw, or its log deleted) is only
    overwritten when the report says it was the same evaluation."""
    p = run_dir / "episodes.json"
    if not p.is_file():
        return
    try:
        old = json.loads(p.read_text()).get("meta", {}).get("fingerprint")
    except (OSError, ValueError, AttributeError):
        old = None
    if old != fp:
        raise RunFolderError(f"{str(run_dir)!r} already holds an evaluation report of another (or an unknown) "
                             f"configuration and no episode log to resume from; {hint or 'give a new output folder'}",
                             value=run_dir)


class EvaluateRunFolderCheck(LockedRunFolderCheck):
    """Hydra callback (conf/evaluate.yaml): ``LockedRunFolderCheck``'s checks, with the evaluation's lock
    (``.evaluate.lock``, which the episode log then keeps for the run): a folder another evaluation is
    writing is refused in one line naming it (exit status 2) and left as it is; what the folder held is
    noted under the lock, so that the app puts it back as it was (``undo_run_folder``) when it refuses the
    run later (another evaluation's episodes, a bad checkpoint)."""

    def lock(self, folder: str, config: Any) -> FolderLock:
        return RunFolderLock(folder)

    def on_run_start(self, config: Any, **kwargs: Any) -> None:
        _check_name_lengths(Path(str(config.hydra.run.dir)), "hydra.run.dir")
        super().on_run_start(config, **kwargs)

    def on_multirun_start(self, config: Any, **kwargs: Any) -> None:
        _check_name_lengths(Path(str(config.hydra.sweep.dir)), "hydra.sweep.dir")
        check_same_sweep(Path(str(config.hydra.sweep.dir)), list(config.hydra.overrides.task))
        super().on_multirun_start(config, **kwargs)


def _check_name_lengths(folder: Path, key: str) -> None:
    """``check_name_lengths`` as one line (exit status 2): before the folder's lock or sweep record is looked
    up, which a name too long for the filesystem makes a traceback."""
    try:
        check_name_lengths(folder, key)
    except RunFolderError as err:
        print(f"cicfw: error: {err}", file=sys.stderr)
        sys.exit(2)


def check_same_sweep(folder: Path, task: list[str]) -> None:
    """A sweep folder resumes only the same sweep: Hydra writes ``multirun.yaml`` and each job's ``.hydra``
    before a job can refuse another evaluation's episodes, so another sweep there would leave the record of
    the first sweep, and of its finished jobs, describing settings their episodes were not driven with.
    One line (exit status 2) naming both override lists; a folder without ``multirun.yaml`` passes."""
    record = folder / "multirun.yaml"
    if not record.is_file():
        return
    try:
        before = OmegaConf.select(OmegaConf.load(record), "hydra.overrides.task")
    except Exception:  # an unreadable record: no sweep this app can resume
        before = None
    before = [str(o) for o in before] if before is not None else None
    if before != [str(o) for o in task]:
        print(f"cicfw: error: the sweep folder {str(folder)!r} holds another sweep ({' '.join(before or ['?'])}), "
              f"not this one ({' '.join(map(str, task))}), which would write over its records; give a fresh "
              f"folder (hydra.sweep.dir=<new folder>) or rerun that sweep's own command to resume it",
              file=sys.stderr)
        sys.exit(2)


class EvaluationBusy(RunFolderError, FolderBusy):
    """Another evaluation holds the run folder (a ``FolderBusy``: its files are left as they are)."""


class RunFolderLock(FolderLock):
    """An evaluation's hold on its run folder: a second evaluation into it is refused naming the first."""

    lock_name = LOCK_NAME

    def busy(self, holder: Mapping[str, Any], waited: float, certain: bool) -> Exception:
        return EvaluationBusy(f"another evaluation (pid {holder.get('pid', '?')}) is writing {str(self.folder)!r}; "
                              f"wait for it to finish or give another output folder", value=self.folder)
