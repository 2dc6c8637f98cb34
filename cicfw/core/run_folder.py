"""A run's folder, checked before anything is written there, refusals as one line (exit status 2).

``check_run_folder``: a read-only folder, a name longer than the filesystem allows or a path through a
file. ``hold_train_folder``: a training run's folder is its own (its lock, no other run's outputs), and
a run refused before it trains leaves it as it found it (``note_run_folder``, ``undo_run_folder``).
``claim_folder``: the one rule every app applies to the folder it writes (docs/training.md). The Hydra
callbacks ``RunFolderCheck``, ``LockedRunFolderCheck`` (the folder locked, then noted) and
``TrainRunFolderCheck`` apply them before Hydra writes ``.hydra``; a folder is noted for undoing only while
this run holds its lock, so a refused run never undoes another's files.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, NoReturn, Sequence

from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from hydra.types import RunMode
from omegaconf import OmegaConf

from cicfw.core.errors import CicfwError, ConfigError
from cicfw.core.files import PROBE_PREFIX, atomic_write, remove_stale_temps, unshare_links, writable_folder
from cicfw.core.locks import FolderBusy, FolderLock, describe_holder
from cicfw.core.slurm_requeue import is_requeued_run, saved_config
from cicfw.core.sweeps import ROWS_DIR, SWEEP_FILE, is_worker_process


class RunFolderError(CicfwError):
    """The run folder cannot be created or written; the message says why and which key to change."""


def name_max(folder: Path) -> int:
    """The longest file name (bytes) the filesystem of ``folder`` (or its nearest existing parent) takes."""
    p = Path(os.path.abspath(folder))
    while not _exists(p) and p != p.parent:
        p = p.parent
    try:
        return int(os.pathconf(p, "PC_NAME_MAX"))
    except (OSError, ValueError):
        return 255


def _exists(p: Path) -> bool:
    """``p.exists()``, False for a path the system refuses to look up (a name that is too long)."""
    try:
        return p.exists()
    except OSError:
        return False


def _check_names(names: Sequence[tuple[str, str]], limit: int) -> None:
    """A ``RunFolderError`` for the first (key, name) whose name is longer than ``limit`` bytes."""
    for key, name in names:
        size = len(os.fsencode(name))
        if size > limit:
            raise RunFolderError(f"{key}: the name {name[:20]}... is {size} bytes long, more than this filesystem "
                                 f"allows ({limit}); give a shorter one")


def check_name_lengths(folder: str | Path, key: str, files: Sequence[tuple[str, str]] = ()) -> None:
    """A ``RunFolderError`` naming ``key`` when a name in ``folder``'s path (or one of ``files``' (key, name)
    pairs) is longer than its filesystem takes: checked before the path is looked up, which would fail with
    a traceback (``File name too long``)."""
    _check_names([(key, part) for part in Path(folder).parts] + list(files), name_max(Path(folder)))


def check_run_folder(folder: str | Path, key: str = "hydra.run.dir", files: Sequence[tuple[str, str]] = ()) -> None:
    """Create ``folder`` (if needed) and a file in it (``writable_folder``): a ``ConfigError`` naming ``key``
    otherwise, or a ``RunFolderError`` for a name longer than the filesystem takes.

    ``files``: (key, file name) pairs the run will create there (the job's log), checked for length."""
    folder = Path(folder)
    if folder.parts and folder.parts[0].startswith("~"):  # Hydra does not expand it: "~/runs" is ./~/runs
        raise ConfigError(key, str(folder), "a path without a leading '~', which Hydra does not expand (it would "
                                            "make a folder named '~' here); give the full path, e.g. $HOME/...")
    check_name_lengths(folder, key, files)
    writable_folder(folder, key, "a folder you can write", "the run folder")


def data_folders(config: Any) -> list[str]:
    """The app's data folder (``data.path``) as ``claim_folder``'s ``data``: none where it has none (the
    Hydra callbacks, and ``cicfw.train.app.train`` claiming its folder through the Python API)."""
    try:
        data = OmegaConf.select(config, "data.path", default=None)
    except Exception:  # an interpolation that does not resolve: the app's own checks name it
        return []
    return [data] if data else []


class RunFolderCheck(Callback):
    """Hydra callback: the run folder (or the sweep folder) checked before the job starts."""

    def on_run_start(self, config: Any, **kwargs: Any) -> None:
        job = str(config.hydra.job.name)
        self.claim(config)
        self._check(config.hydra.run.dir, "hydra.run.dir", [("hydra.job.name", f"{job}.log")])

    @staticmethod
    def claim(config: Any) -> None:
        """``claim_folder`` for the run folder, the app named by Hydra's job name (what Hydra records there),
        the data folder being ``data.path`` where the app has one; one line (exit status 2) when refused."""
        folder = str(config.hydra.run.dir)
        if is_worker_process():  # a DDP rank Lightning re-runs as job 'train_ddp_process_<k>' in its rank 0's folder
            return
        try:
            claim_folder(folder, str(config.hydra.job.name), "hydra.run.dir", data=data_folders(config))
        except RunFolderError as err:
            forget_run_folder(folder)  # nothing was written: nothing to put back
            print(f"cicfw: error: {err}", file=sys.stderr)
            sys.exit(2)

    def on_run_end(self, config: Any, **kwargs: Any) -> None:
        # after the app's job, which put the folder back itself if it refused the run: a folder that is a
        # run's now is never put back later (another app refused in the same process, undo_noted_folders)
        forget_run_folder(str(config.hydra.run.dir))

    def on_multirun_start(self, config: Any, **kwargs: Any) -> None:
        job = str(config.hydra.job.name)
        app = None if is_worker_process() else job  # a DDP rank re-running its rank 0's sweep finds it there
        try:
            claim_sweep_folder(str(config.hydra.sweep.dir), data=data_folders(config), app=app)
        except RunFolderError as err:
            print(f"cicfw: error: {err}", file=sys.stderr)
            sys.exit(2)
        if not is_worker_process():  # a DDP rank re-running the sweep of its rank 0 shares its folder
            note_run_folder(str(config.hydra.sweep.dir))  # undone if a job's config is refused up front
        self._check(config.hydra.sweep.dir, "hydra.sweep.dir", [("hydra.job.name", f"{job}.log")])

    def on_job_start(self, config: Any, **kwargs: Any) -> None:
        if config.hydra.mode == RunMode.MULTIRUN:  # a job runs: the sweep folder is the sweep's now
            forget_run_folder(str(config.hydra.sweep.dir))

    @staticmethod
    def _check(folder: Any, key: str, files: Sequence[tuple[str, str]]) -> None:
        try:
            check_run_folder(str(folder), key, files)
        except CicfwError as err:  # a RunFolderError, or writable_folder's ConfigError
            print(f"cicfw: error: {err}", file=sys.stderr)
            sys.exit(2)


# ---- a training run's folder is its own ------------------------------------------------------------
#: what a training run leaves in its folder (relative paths): another run's, when found at the start
RUN_OUTPUTS = ("checkpoints", "csv/metrics.csv", "tensorboard", "metrics.json", "evaluate")
#: ``ckpt_path`` values Lightning resolves inside the run's own folder
OWN_CHECKPOINT_NAMES = ("last", "best", "hpc")


def run_outputs(folder: str | Path) -> list[str]:
    """The training outputs ``folder`` holds (``RUN_OUTPUTS`` that exist and are not empty folders)."""
    folder = Path(folder)
    found = []
    for name in RUN_OUTPUTS:
        p = folder / name
        if p.is_file() or (p.is_dir() and any(p.iterdir())):
            found.append(name)
    return found


def resumes_inside(folder: str | Path, ckpt_path: Any) -> bool:
    """Whether ``ckpt_path`` is one of ``folder``'s own checkpoints (a file inside it, or a name Lightning
    resolves there): resuming that run, not starting another over it."""
    if ckpt_path is None or str(ckpt_path) == "":
        return False
    if str(ckpt_path) in OWN_CHECKPOINT_NAMES:
        return True
    ckpt = Path(os.path.realpath(Path(str(ckpt_path)).expanduser()))
    return Path(os.path.realpath(folder)) in ckpt.parents


def check_no_other_run(folder: str | Path, ckpt_path: Any = None, key: str = "hydra.run.dir",
                       config: Any = None) -> None:
    """One ``RunFolderError`` when ``folder`` holds another run's outputs (which this run would cut or
    replace), unless ``ckpt_path`` resumes from a checkpoint inside it, or, with no ``ckpt_path``, this is
    a SLURM job requeued into its own folder (``is_requeued_run`` with ``config``, the command's composed
    config), which Lightning resumes from its HPC checkpoint (checked as ``ckpt_path=hpc``)."""
    found = run_outputs(folder)
    if not found or resumes_inside(folder, ckpt_path):
        return
    if (ckpt_path is None or str(ckpt_path) == "") and is_requeued_run(folder, config):
        return
    last = Path(folder) / "checkpoints" / "last.ckpt"
    resume = f" or resume that run with ckpt_path={last}" if last.is_file() else ""
    raise RunFolderError(f"the run folder {str(folder)!r} already holds another run's outputs ({', '.join(found)}), "
                         f"which this run would replace; give a fresh folder ({key}=<new folder>){resume}",
                         key=key, value=folder)


class AppFolderLock(FolderLock):
    """``<run folder>/.<app>.lock`` (or ``lock_name``): one run of ``app`` per folder, refused in one line
    naming the holder."""

    def __init__(self, folder: str | Path, app: str, key: str = "hydra.run.dir", lock_name: str | None = None) -> None:
        self.lock_name, self.app, self.key = lock_name or f".{app}.lock", app, key
        super().__init__(folder)

    def busy(self, holder: Mapping[str, Any], waited: float, certain: bool) -> Exception:
        tail = "" if certain else f"; if it is no longer running, delete {str(self.path)!r}"
        return FolderBusy(f"the run folder {str(self.folder)!r} is in use by another cicfw {self.app} run "
                          f"({describe_holder(holder)}); give a fresh folder ({self.key}=<new folder>) or wait for "
                          f"it to finish{tail}", key=self.key, value=self.folder)

    def unusable(self, err: OSError, step: str) -> Exception:
        return RunFolderError(f"cannot lock the run folder {str(self.folder)!r} ({err.strerror or err}); give a "
                              f"local folder you can write: {self.key}=<folder>", key=self.key, value=self.folder)


class TrainFolderLock(AppFolderLock):
    """``<run folder>/.train.lock``: one training run per folder, held while it runs."""

    activity = "trains into it"

    def __init__(self, folder: str | Path, key: str = "hydra.run.dir") -> None:
        super().__init__(folder, "train", key)


_HELD: dict[str, TrainFolderLock] = {}  # the run folders this process holds, by absolute path


def hold_train_folder(folder: str | Path, ckpt_path: Any = None, key: str = "hydra.run.dir",
                      config: Any = None) -> None:
    """Make ``folder`` this process's training folder: its lock taken (unless this process holds it
    already), then ``check_no_other_run`` (``config``: the command's, for a requeued SLURM job), the lock
    given back when that fails. One line otherwise:
    ``FolderBusy`` (another run holds it) or ``RunFolderError``. A DDP worker rank (its ``RANK`` ...
    not 0) shares the folder rank 0 holds: nothing to take. Held, the folder loses the temporary files a
    killed writer left (``remove_stale_temps``)."""
    if is_worker_process():
        return
    name = os.path.abspath(folder)
    if name not in _HELD:
        _HELD[name] = TrainFolderLock(name, key).acquire()
    try:
        check_no_other_run(folder, ckpt_path, key, config)
    except RunFolderError:
        release_run_folder(folder)
        raise
    remove_stale_temps(folder)  # a killed run's half-written checkpoint or record, never renamed


#: the records Hydra rewrites in a run's ``.hydra`` at every start, a resumed run's included
HYDRA_RECORDS = ("config.yaml", "overrides.yaml", "hydra.yaml")


def keep_segment_records(folder: str | Path) -> int | None:
    """Copy the ``HYDRA_RECORDS`` of ``folder``'s earlier segment to ``.hydra/<name>.<k>.yaml`` before Hydra
    rewrites them for a resume, so the config each segment trained with stays readable. ``k`` is the first
    number no kept record has (as ``metrics.<k>.csv``: the k-th resume keeps ``.k``); a kept file is never
    replaced. Returns ``k``, None when there is no record to keep."""
    hydra = Path(folder) / ".hydra"
    found = [name for name in HYDRA_RECORDS if (hydra / name).is_file()]
    if not found:
        return None
    k = 1
    while any(_exists(hydra / f"{Path(name).stem}.{k}.yaml") for name in HYDRA_RECORDS):
        k += 1
    for name in found:
        atomic_write(hydra / f"{Path(name).stem}.{k}.yaml", (hydra / name).read_bytes())
    return k


def forget_failed_run(folder: str | Path) -> list[str]:
    """A training run that stopped before writing any checkpoint leaves nothing to resume from, and its
    error says to run the same command again: the outputs it wrote (``run_outputs``: the metrics it logged
    ...) are removed, so that command is not refused as another run's folder (the log and ``.hydra`` stay).
    Only for a folder this run held from an empty start (``hold_train_folder``). Returns what was removed."""
    folder = Path(folder)
    if any((folder / "checkpoints").glob("*.ckpt")):
        return []
    found = run_outputs(folder)
    for name in found:
        p = folder / name
        shutil.rmtree(p, ignore_errors=True) if p.is_dir() and not p.is_symlink() else p.unlink(missing_ok=True)
    return found


def release_run_folder(folder: str | Path) -> None:
    """Give up the lock ``hold_train_folder`` took on ``folder`` (nothing when this process holds none)."""
    lock = _HELD.pop(os.path.abspath(folder), None)
    if lock is not None:
        lock.release()


# ---- a refused run leaves nothing behind -------------------------------------------------------------
@dataclass
class FolderBefore:
    """What a run folder held before a run wrote into it: whether it existed (and the first of its parents
    that did not), its entries, the bytes of its ``.hydra`` files and the size of its logs."""

    existed: bool
    first_made: Path | None = None
    entries: set[str] = field(default_factory=set)
    hydra_files: dict[str, bytes] = field(default_factory=dict)
    log_sizes: dict[str, int] = field(default_factory=dict)


_BEFORE: dict[str, FolderBefore] = {}  # run folders noted by note_run_folder, by absolute path


def note_run_folder(folder: str | Path) -> None:
    """Note what ``folder`` holds now, before Hydra creates it or writes ``.hydra`` and the job's log."""
    folder = Path(os.path.abspath(folder))
    if not _exists(folder):
        first = folder
        while not _exists(first.parent) and first.parent != first:
            first = first.parent
        _BEFORE[str(folder)] = FolderBefore(existed=False, first_made=first)
        return
    try:
        hydra = {str(p.relative_to(folder)): p.read_bytes() for p in (folder / ".hydra").glob("*") if p.is_file()}
        logs = {p.name: p.stat().st_size for p in folder.glob("*.log") if p.is_file()}
        _BEFORE[str(folder)] = FolderBefore(True, None, {p.name for p in folder.iterdir()}, hydra, logs)
    except OSError:
        pass  # an unreadable folder: check_run_folder says so; nothing will be undone in it


def forget_run_folder(folder: str | Path) -> None:
    """Drop ``folder``'s note: nothing of it is to be put back (nothing was written, or it is a run's now)."""
    _BEFORE.pop(os.path.abspath(folder), None)


def saved_run_config(checkpoint: str | Path) -> Any | None:
    """The config the training run that wrote ``checkpoint`` (``<run>/checkpoints/x.ckpt``) saved in
    ``<run>/.hydra/config.yaml`` (``saved_config``). A Hydra run resuming in that same folder has already
    rewritten that file with its own command: the earlier segment's record is read then, the newest
    ``config.<k>.yaml`` ``keep_segment_records`` kept."""
    run = Path(checkpoint).parent.parent
    kept = newest_kept_record(run) if _is_this_runs_folder(run) else None
    return saved_config(run) if kept is None else saved_config(run, kept.name)


def newest_kept_record(folder: str | Path) -> Path | None:
    """The newest earlier segment's config ``keep_segment_records`` kept in ``folder``, or None."""
    numbered = [(int(p.name.split(".")[1]), p) for p in (Path(folder) / ".hydra").glob("config.*.yaml")
                if p.name.split(".")[1].isdigit()]
    return max(numbered)[1] if numbered else None


def _is_this_runs_folder(folder: Path) -> bool:
    """Whether ``folder`` is the output folder of the Hydra run this process is."""
    if not HydraConfig.initialized():
        return False
    try:  # realpath: the run folder and the checkpoint's path may name it through a symlink or not
        return os.path.realpath(HydraConfig.get().runtime.output_dir) == os.path.realpath(folder)
    except Exception:  # a Hydra config without a runtime folder: not a run
        return False


def undo_run_folder(folder: str | Path, hydra_only: bool = False) -> None:
    """Put ``folder`` back as ``note_run_folder`` found it: removed, with the parents made for it, when it
    did not exist; else what the run added removed, ``.hydra`` rewritten as it was and the logs cut back.
    ``hydra_only``: of what was added to a folder that existed, remove only Hydra's ``.hydra`` and job log
    (after a long check, when another writer may have added files meanwhile). Nothing happens to a folder
    that was not noted (a multirun job's folder keeps its log)."""
    folder = Path(os.path.abspath(folder))
    before = _BEFORE.pop(str(folder), None)
    if before is None or not _exists(folder):
        return
    if not before.existed:
        shutil.rmtree(folder, ignore_errors=True)
        parent = folder.parent
        while before.first_made is not None and before.first_made in (parent, *parent.parents):
            try:
                parent.rmdir()  # only while empty: another run may have written beside it since
            except OSError:
                break
            parent = parent.parent
        return
    for entry in folder.iterdir():
        if entry.name not in before.entries and not (hydra_only and entry.name != ".hydra" and entry.suffix != ".log"):
            shutil.rmtree(entry, ignore_errors=True) if entry.is_dir() and not entry.is_symlink() else entry.unlink()
    for p in (folder / ".hydra").glob("*") if before.hydra_files else ():
        if str(p.relative_to(folder)) not in before.hydra_files:
            p.unlink()
    for rel, data in before.hydra_files.items():
        (folder / rel).write_bytes(data)
    for name, size in before.log_sizes.items():
        if (folder / name).is_file():
            os.truncate(folder / name, size)


def undo_noted_folders() -> None:
    """``undo_run_folder`` for every folder noted and not yet undone or forgotten: the app stopped before
    running a job (Hydra refused a job's config while the sweeper checked the sweep)."""
    for folder in list(_BEFORE):
        undo_run_folder(folder)


def refuse_before_any_job(line: str) -> NoReturn:
    """A run refused before its first job: ``line`` as the one ``cicfw: error:`` line, the folders noted for
    it put back (``undo_noted_folders``: a sweep folder made already), exit status 2."""
    print(f"cicfw: error: {line}", file=sys.stderr)
    undo_noted_folders()
    sys.exit(2)


def check_no_other_sweep(folder: str | Path, key: str = "hydra.sweep.dir") -> None:
    """One ``RunFolderError`` when ``folder`` holds another multirun (its ``multirun.yaml``, or a job folder
    with Hydra's record), which this one would write over before any of its jobs could refuse."""
    folder = Path(folder)
    if not folder.is_dir():
        return
    jobs = sorted(p.name for p in folder.iterdir() if (p / ".hydra").is_dir())
    if not jobs and not (folder / "multirun.yaml").is_file():
        return
    held = ["multirun.yaml"] if (folder / "multirun.yaml").is_file() else []
    held += [f"{len(jobs)} job folder(s): {', '.join(jobs[:5])}{' ...' if len(jobs) > 5 else ''}"] if jobs else []
    raise RunFolderError(f"the sweep folder {str(folder)!r} already holds another multirun ({'; '.join(held)}), "
                         f"which this one would write over; give a fresh folder ({key}=<new folder>)")


# ---- a run folder held from before Hydra writes there --------------------------------------------------
_LOCKS: dict[str, FolderLock] = {}  # the run-folder locks this process holds, by the lock file's real path


def _lock_key(path: str | Path) -> str:
    return os.path.realpath(path)


def hold_folder_lock(lock: FolderLock) -> FolderLock:
    """Take ``lock`` (its refusal raised as the lock words it) and keep it for this process until
    ``release_folder_locks`` (or an app's ``take_held_lock``) takes it."""
    held = _LOCKS.get(_lock_key(lock.path))
    if held is not None:
        return held
    _LOCKS[_lock_key(lock.path)] = lock.acquire()
    return lock


def take_held_lock(path: str | Path) -> FolderLock | None:
    """The lock at ``path`` (a lock file) this process holds through ``hold_folder_lock``, handed over to
    the caller (who releases it, or gives it back with ``keep_held_lock``); None when none is held."""
    return _LOCKS.pop(_lock_key(path), None)


def keep_held_lock(lock: FolderLock) -> None:
    """Give a lock ``take_held_lock`` handed over back to this process's held locks."""
    _LOCKS[_lock_key(lock.path)] = lock


def release_folder_locks(folder: str | Path) -> None:
    """Let go of every lock this process holds on ``folder`` (nothing when it holds none)."""
    folder = os.path.realpath(folder)
    for key in [k for k in _LOCKS if os.path.dirname(k) == folder]:
        _LOCKS.pop(key).release()


def let_go_unheld(folder: str | Path, err: Exception) -> None:
    """A run refused before it held ``folder`` (``err``): another run's folder (it holds it, or wrote into it)
    is left as it is, but a folder made for this run that holds nothing but cicfw's housekeeping (its lock
    could not be used: a file system without ``flock``) goes again, as ``undo_run_folder`` removes it."""
    before = _BEFORE.get(os.path.abspath(folder))
    if (not isinstance(err, FolderBusy) and before is not None and not before.existed
            and not _entries(Path(folder))):
        undo_run_folder(folder)
    else:
        forget_run_folder(folder)


def _renote_held_folder(folder: str | Path) -> None:
    """Note ``folder`` again once this run holds it: what another run wrote there before it let go is no
    longer this run's to remove. A folder that was missing at the first note and holds nothing yet (but
    locks and write probes) stays noted as missing: undone, it goes whole."""
    before = _BEFORE.get(os.path.abspath(folder))
    if before is not None and not before.existed and not _entries(Path(folder)):
        return
    note_run_folder(folder)


class LockedRunFolderCheck(RunFolderCheck):
    """Hydra callback (conf/diagnose.yaml; collect's and evaluate's subclass it): ``RunFolderCheck``'s checks,
    then the run folder locked for this run (``lock``; the job name's ``.<job>.lock``) before Hydra writes
    ``.hydra`` and the job's log there, and only then what it holds noted, so that the app puts it back
    (``undo_run_folder``, under the lock) when it refuses the run later. A folder another run of the app
    holds is one line (exit status 2), its files untouched: noting and undoing happen only while this run
    holds the folder."""

    def lock(self, folder: str, config: Any) -> FolderLock:
        """The lock this app's runs take on their folder."""
        return AppFolderLock(folder, _job_app(str(config.hydra.job.name)))

    def on_run_start(self, config: Any, **kwargs: Any) -> None:
        folder = str(config.hydra.run.dir)
        note_run_folder(folder)  # whether it exists yet: a folder made for this run is removed whole if undone
        # the lock by its absolute path: hydra.job.chdir=true moves the job into a relative run folder before the
        # app lets go of it, and a lock file not found by its path then would stay behind as a stale one
        lock, worker = self.lock(os.path.abspath(folder), config), is_worker_process()  # a DDP rank: rank 0 holds it
        if not worker and _exists(lock.path):  # another run's (or a dead one's): its holder named before the checks
            self._hold(folder, lock)
        try:
            super().on_run_start(config, **kwargs)
        except SystemExit:  # refused before Hydra wrote anything: nothing to put back
            forget_run_folder(folder)
            release_folder_locks(folder)
            raise
        if not worker:
            self._hold(folder, lock)
            _renote_held_folder(folder)
            try:  # held: another app's run (its own lock) may have taken the folder since the checks
                self.claim(config)
            except SystemExit:
                release_folder_locks(folder)
                raise

    @staticmethod
    def _hold(folder: str, lock: FolderLock) -> None:
        """``hold_folder_lock``, or one line (exit status 2) when the folder cannot be held: another run's
        files stay as they are (``let_go_unheld``)."""
        try:
            hold_folder_lock(lock)
        except (CicfwError, OSError) as err:
            if not isinstance(err, CicfwError):  # a lock that words no error of its own when it cannot be used
                err = RunFolderError(f"cannot lock the run folder {folder!r} ({err.strerror or err}); give a local "
                                     f"folder you can write: hydra.run.dir=<folder>", key="hydra.run.dir", value=folder)
            let_go_unheld(folder, err)
            print(f"cicfw: error: {err}", file=sys.stderr)
            sys.exit(2)

    def on_run_end(self, config: Any, **kwargs: Any) -> None:
        release_folder_locks(str(config.hydra.run.dir))
        super().on_run_end(config, **kwargs)


class TrainRunFolderCheck(RunFolderCheck):
    """Hydra callback (conf/train.yaml): ``RunFolderCheck``'s checks, then the run folder held for this run
    (``hold_train_folder``) before Hydra writes its ``.hydra`` there, and what it held noted for
    ``undo_run_folder``; a folder another run holds or wrote into, or a sweep folder holding another
    multirun, is one line (exit status 2), the other run's files untouched. A resume keeps the earlier
    segment's ``.hydra`` records first (``keep_segment_records``)."""

    def on_run_start(self, config: Any, **kwargs: Any) -> None:
        folder = str(config.hydra.run.dir)
        note_run_folder(folder)
        super().on_run_start(config, **kwargs)
        try:
            hold_train_folder(folder, config.get("ckpt_path"), "hydra.run.dir", config)
        except ValueError as err:  # another run holds it or wrote into it: its files, nothing to put back
            let_go_unheld(folder, err)  # (a folder made for this run, whose lock could not be used, goes)
            print(f"cicfw: error: {err}", file=sys.stderr)
            sys.exit(2)
        _renote_held_folder(folder)  # held: what another run left there before is no longer this run's to undo
        try:  # held: another app's run (its own lock) may have taken the folder since the checks
            self.claim(config)
        except SystemExit:
            release_run_folder(folder)
            raise
        if is_worker_process() or not run_outputs(folder):  # a rank of rank 0's run, or a fresh run
            return
        try:  # held with outputs: this run resumes the folder's, whose records Hydra is about to rewrite
            keep_segment_records(folder)  # undo_run_folder removes the copies again if the resume is refused
        except OSError as err:
            release_run_folder(folder)
            undo_run_folder(folder)
            print(f"cicfw: error: cannot keep the earlier segment's config in {folder}/.hydra "
                  f"({err.strerror or err}); hydra.run.dir must be a run folder you can write", file=sys.stderr)
            sys.exit(2)

    def on_multirun_start(self, config: Any, **kwargs: Any) -> None:
        if not is_worker_process():  # a DDP rank re-running the sweep of its rank 0 shares its folder
            try:
                check_no_other_sweep(str(config.hydra.sweep.dir))
            except RunFolderError as err:
                print(f"cicfw: error: {err}", file=sys.stderr)
                sys.exit(2)
        super().on_multirun_start(config, **kwargs)

    def on_run_end(self, config: Any, **kwargs: Any) -> None:
        release_run_folder(str(config.hydra.run.dir))
        super().on_run_end(config, **kwargs)


# ---- every app writes only into a folder of its own -----------------------------------------------
#: files cicfw itself leaves beside a run's outputs (locks, write probes): they make no folder anyone's
HOUSEKEEPING = (".lock", ".train.lock", ".evaluate.lock", ".collect.lock", ".collect-run.lock", ".diagnose.lock",
                "reproduce.lock")
#: the record each non-Hydra output names itself by: (file, app); an evaluation's by its episode log's header
#: (``holds_episode_log``), a reproduction stopped before its manifest by its cell tree (``is_reproduction_results``)
RECORDS = (("report.json", "report"), ("reproduce.json", "reproduce"), ("dataset_metadata.json", "collect"))
#: an evaluation's episode log and the format its first line (the header) names: the log is evaluate's only
#: with that header (``cicfw.benchmark.journal``), not any file of that name
EPISODE_LOG, EPISODE_LOG_FORMAT = "episodes.jsonl", "cicfw-episode-log/1"
#: the keys (and their types) a training run's data record (``data.json``, ``cicfw.data.provenance``) holds, all
#: of them: a manifest holding only a ``path`` and ``files`` is no proof
DATA_RECORD_KEYS = (("path", str), ("root", str), ("files", list), ("hash", str), ("hash_of", str), ("n_files", int))
#: a reproduction's own log in its results folder: no proof (a shell redirect makes it), but no file of
#: another's either when ``reproduce`` claims the folder
REPRODUCE_LOG = "reproduce.log"
#: what a dataset's files end with: a folder holding them is someone's data, whoever collected it
DATA_SUFFIXES = (".h5", ".hdf5")
#: a Hydra app's run without ``.hydra`` (``hydra.output_subdir=null``): its job log ``<job>.log`` together with
#: one of the outputs only that app writes there (evaluate's episode log names it already). The log
#: alone is no proof (any tool may write a ``train.log``), nor are the outputs alone (a copy of a checkpoint)
JOB_OUTPUTS = (("train", ("checkpoints", "csv/metrics.csv", "metrics.json", "data.json")),
               ("diagnose", ("steer_diagnostic.json",)))
#: a training run through the Python API (``cicfw.train.app.train``: the reproduction's cells, a notebook) has
#: neither ``.hydra`` nor a log: its record of its data (``data.json``) beside one of these outputs names it
TRAIN_API_OUTPUTS = ("checkpoints", "csv/metrics.csv", "metrics.json")


def _entries(folder: Path) -> list[str]:
    """The names in ``folder`` that are not cicfw housekeeping (``[]`` for a missing folder or a file)."""
    try:
        names = sorted(p.name for p in folder.iterdir())
    except OSError:  # missing, a file, or unreadable: check_run_folder (or the app's own check) says so
        return []
    return [n for n in names if n not in HOUSEKEEPING and not n.startswith(PROBE_PREFIX)]


def _hydra_job(folder: Path) -> str | None:
    """The job name Hydra recorded for the run (``.hydra/hydra.yaml``) or the sweep (``multirun.yaml``) in
    ``folder``; for a ``.hydra`` without ``hydra.yaml``, the name of the job log beside it (``<job>.log``)."""
    for record in (folder / ".hydra" / "hydra.yaml", folder / "multirun.yaml"):
        if record.is_file():
            try:
                name = OmegaConf.select(OmegaConf.load(record), "hydra.job.name")
            except Exception:  # an unreadable record: its folder is still a Hydra run, of no app we know
                name = None
            return str(name) if name else "an unnamed Hydra job"
    if (folder / ".hydra").is_dir():
        logs = sorted(p.stem for p in folder.glob("*.log") if p.is_file())
        return logs[0] if len(logs) == 1 else None
    return None


def _trained_through_api(folder: Path) -> bool:
    """Whether ``folder`` is a training run through the Python API: its data record beside its outputs."""
    return _holds_data_record(folder) and any(_exists(folder / name) for name in TRAIN_API_OUTPUTS)


def is_reproduction_results(folder: str | Path) -> bool:
    """Whether ``folder`` is a reproduction's results folder: its manifest (``reproduce.json``), or the cell
    tree (``cells/<row>/seed<k>`` folders) of a run stopped before writing it; a cell itself is none."""
    folder = Path(folder)
    return (folder / "reproduce.json").is_file() or any(
        p.is_dir() and re.fullmatch(r"seed\d+", p.name) for p in (folder / "cells").glob("*/seed*"))


def holds_episode_log(folder: str | Path) -> bool:
    """Whether ``folder``'s ``episodes.jsonl`` opens with cicfw's episode-log header (its first line, a JSON
    object naming ``EPISODE_LOG_FORMAT``): an evaluation's log, not any file of that name."""
    try:
        with open(Path(folder) / EPISODE_LOG, "rb") as f:
            first = f.readline(1 << 22)
        header = json.loads(first)
    except (OSError, ValueError):
        return False
    return isinstance(header, dict) and header.get("format") == EPISODE_LOG_FORMAT


def _cicfw_hydra_run(folder: Path) -> bool:
    """Whether ``folder``'s ``.hydra/hydra.yaml`` is a cicfw app's: its ``hydra.callbacks`` (every cicfw app
    config names its own) include one of cicfw's classes, which a script of another project does not."""
    try:
        callbacks = OmegaConf.select(OmegaConf.load(folder / ".hydra" / "hydra.yaml"), "hydra.callbacks")
        targets = [str(c.get("_target_", "")) for c in callbacks.values()] if callbacks else []
    except Exception:  # missing or unreadable: no proof
        return False
    return any(t.startswith("cicfw.") for t in targets)


def _job_app(job: str) -> str:
    """The app of a Hydra job name (a DDP rank's job is ``<app>_ddp_process_<k>``)."""
    return job.split("_ddp_process_")[0]


def _unvouched_outputs(folder: Path, app: str) -> list[str]:
    """The files of ``OWN_OUTPUTS[app]`` in ``folder`` without the record that proves ``app`` wrote them."""
    if app not in OWN_OUTPUTS:
        return []
    outputs, vouches, _ = OWN_OUTPUTS[app]
    return [] if vouches(folder) else [n for n in outputs if os.path.lexists(folder / n)]


def _holds_data_record(folder: Path) -> bool:
    """Whether ``folder/data.json`` is a training run's record of its data (``DATA_RECORD_KEYS``, all of them:
    its path, its files and their hash), not any file of that name."""
    try:
        record = json.loads((folder / "data.json").read_text())
    except (OSError, ValueError):
        return False
    return isinstance(record, dict) and all(isinstance(record.get(k), t) and not isinstance(record.get(k), bool)
                                            for k, t in DATA_RECORD_KEYS)


#: the files an app writes over in a run folder of its own (``folder_owner``), the check of the record that vouches
#: for them there, and that record: without it they are the user's, whatever ``.hydra`` (a copy proves nothing) says
OWN_OUTPUTS = {"evaluate": (("episodes.json", "episodes.csv", "summary.json", "table.md", "table.tex"),
                            holds_episode_log, "episode log (episodes.jsonl with cicfw's header)"),
               "train": (("data.json",), _holds_data_record, "record of its data (data.json holding cicfw's keys)")}


def folder_owner(folder: str | Path) -> str | None:
    """The app whose run (or output) ``folder`` is, from the record that app already leaves there: Hydra's
    job name for a Hydra app (train, evaluate, ...; an ``evaluate`` job only with cicfw's callbacks in its
    ``hydra.yaml`` or cicfw's episode log beside it) or, without ``.hydra``, its job log beside its outputs
    (``JOB_OUTPUTS``), a training run's data record without either (``data.json`` holding every key of
    cicfw's record, which only ``train`` writes, once its checks passed: beside its outputs, or alone where
    the run stopped before its first one), the episode log of an evaluation driven through the Python API
    (``episodes.jsonl`` opening with cicfw's header), ``report.json`` for a report, ``reproduce.json`` (or its
    ``cells/<row>/seed<k>`` tree, where a run stopped before it wrote the manifest) for a reproduction,
    ``dataset_metadata.json`` or HDF5 files for a dataset ("collect"); None for none (results copied out of
    their run folder are no run: their episode log stays behind). A file's name alone that a user may
    give their own file (``reproduce.log``, ``cells/``, ``episodes.jsonl``, ``data.json``) proves nothing.
    Records the apps write anyway, rather than a new marker file, so that folders written before this
    check are recognised and no app writes a file more than it did."""
    folder = Path(folder)
    job = _hydra_job(folder)
    if job is not None:
        if _job_app(job) == "evaluate" and (folder / ".hydra").is_dir() \
                and not (_cicfw_hydra_run(folder) or holds_episode_log(folder)):
            return None  # another project's Hydra script named evaluate: its results are no cicfw run's
        return job
    for app, outputs in JOB_OUTPUTS:
        if (folder / f"{app}.log").is_file() and any(_exists(folder / name) for name in outputs):
            return app
    if _holds_data_record(folder):  # beside its outputs, or alone: a run stopped before its first output
        return "train"
    if holds_episode_log(folder):
        return "evaluate"
    for name, app in RECORDS:
        if (folder / name).exists():
            return app
    if is_reproduction_results(folder):  # its cell tree, where a run stopped before it wrote the manifest
        return "reproduce"
    if any(name.endswith(DATA_SUFFIXES) for name in _entries(folder)):
        return "collect"
    return None


def _same(a: str | Path, b: str | Path) -> bool:
    """Whether two paths name one folder (through symlinks, ``..`` and ``~``)."""
    return os.path.realpath(Path(a).expanduser()) == os.path.realpath(Path(b).expanduser())


def _listed(names: Sequence[str]) -> str:
    return ", ".join(names[:5]) + (f" and {len(names) - 5} more" if len(names) > 5 else "")


def _refuse_data_folder(folder: Path, data: Sequence[str | Path], key: str, tail: str) -> None:
    """One ``RunFolderError`` naming ``key`` when ``folder`` is one of the data folders ``data``."""
    if any(d is not None and str(d) != "" and _same(folder, d) for d in data):
        raise RunFolderError(f"{key}={str(folder)!r} is the data folder (data.path) {tail}", key=key, value=str(folder))


def claim_sweep_folder(folder: str | Path, key: str = "hydra.sweep.dir", *, data: Sequence[str | Path] = (),
                       app: str | None = None) -> None:
    """A sweep folder holds the sweep's job folders (``0/``, ``1/`` ...) and what it writes beside them (its
    record, summary, joined table): a folder that is itself one run of any app (its own kind too: an
    evaluation's folder would be joined as the sweep's only row), a dataset or the data folder is refused in
    one ``RunFolderError`` naming ``key``. With ``app`` (the sweeping app's job name), so is a folder holding
    another app's sweep or files no sweep of ``app`` wrote (``summary.csv``, ``table.md`` ... would be
    written over them): only an earlier sweep of ``app`` (its ``multirun.yaml``) may hold what it likes. A
    missing or empty folder, an earlier sweep or a folder holding cicfw runs or sweeps below it passes
    (``check_no_other_sweep`` and the apps' own checks see to those)."""
    folder = Path(folder).expanduser()
    where, fix = f"{key}={str(folder)!r}", f"give a folder of its own ({key}=<new folder>)"
    _refuse_data_folder(folder, data, key, f"the sweep's jobs read; {fix}")
    if not _exists(folder) or not folder.is_dir():
        return
    if (folder / "multirun.yaml").is_file() and not (folder / ".hydra").exists():
        job = _hydra_job(folder)
        if app is None or job == app:  # an earlier sweep: whether this one may go on there is the app's own check
            return
        raise RunFolderError(f"{where} holds a sweep of {_app_named(job)} ({_listed(_entries(folder))}), which this "
                             f"cicfw {app} sweep would write over; {fix}", key=key, value=str(folder))
    owner = folder_owner(folder)
    if owner is not None:
        what = "holds a dataset (HDF5 episodes)" if owner == "collect" else f"is a run of cicfw {owner}"
        raise RunFolderError(f"{where} {what}, not a sweep folder: the sweep would write its job folders and its "
                             f"files inside it; {fix}", key=key, value=str(folder))
    foreign = [] if app is None else [n for n in _entries(folder) if not _cicfw_output(folder / n)]
    if foreign:
        raise RunFolderError(f"{where} holds files that no cicfw {app} sweep wrote ({_listed(foreign)}), which the "
                             f"sweep would write over or beside; {fix}", key=key, value=str(folder))


def _app_named(job: str | None) -> str:
    """``cicfw <app>`` for a cicfw app's job name, else the name as ``_hydra_job`` gave it."""
    return f"cicfw {job}" if job in CICFW_APPS else str(job)


#: how deep below a sweep folder's entry a cicfw run may sit for the entry to be cicfw's (Hydra's own layout,
#: ``multirun/<date>/<time>``, puts it two levels down)
OUTPUT_DEPTH = 3


def _cicfw_output(entry: Path, depth: int = OUTPUT_DEPTH) -> bool:
    """Whether ``entry`` (in a folder with no sweep record) is something cicfw wrote there: a folder that is a
    run or a sweep of a cicfw app, or holds only such folders down to ``depth`` levels (``<date>/<time>``
    runs, a folder grouping sweeps), or the row files of a sweep stopped before Hydra wrote its record."""
    if not entry.is_dir() or entry.is_symlink():
        return False
    if entry.name == ROWS_DIR:
        return (entry / SWEEP_FILE).is_file()
    if (entry / "multirun.yaml").is_file() or folder_owner(entry) is not None:
        return True
    inside = [entry / n for n in _entries(entry)]
    return depth > 1 and bool(inside) and all(_cicfw_output(p, depth - 1) for p in inside)


def claim_folder(folder: str | Path, app: str, key: str, *, data: Sequence[str | Path] = (),
                 inputs: Sequence[str | Path] = (), foreign_ok: bool = False) -> None:
    """The one rule every app applies to the folder it writes, before it writes anything there: ``app``
    may write into a folder that is missing, empty (of all but cicfw's locks), or its own kind of run
    (``folder_owner``), where the app's own checks then apply (resume, continue, overwrite). Refused in one
    ``RunFolderError`` naming ``key`` and the folder: the user's data folder (one of ``data``), a folder
    the app reads (one of ``inputs``), another app's run, a folder inside another app's run
    (``claim_outside_runs``, but for the folders cicfw itself nests there, ``NESTED_RUNS``), or files no
    cicfw app wrote (unless ``foreign_ok``: an explicit overwrite option)."""
    folder = Path(folder).expanduser()
    where = f"{key}={str(folder)!r}"
    fix = f"give a fresh folder ({key}=<new folder>)"
    _refuse_data_folder(folder, data, key, f"whose episodes cicfw {app} reads; {fix}")
    for src in inputs:
        if _same(folder, src):
            raise RunFolderError(f"{where} is one of the folders cicfw {app} reads ({src}), whose files it would "
                                 f"replace; {fix}", key=key, value=str(folder))
    entries = _entries(folder)  # [] for a missing folder or a file: the app's own check says what is wrong
    owner = folder_owner(folder) if entries else None
    if owner == app:
        found = enclosing_run(folder)
        if found is not None and found[1] == "reproduce" != app:  # a reproduction's cell: its runs are its own
            claim_outside_runs(folder, app, key, found)
        unvouched = _unvouched_outputs(folder, app)
        if unvouched:
            raise RunFolderError(f"{where} holds {_listed(unvouched)}, which no cicfw {app} run wrote there (its "
                                 f"{OWN_OUTPUTS[app][2]} is missing), and which cicfw {app} would write over; {fix}",
                                 key=key, value=str(folder))
        unshare_links(folder)  # a hard-linked copy of a run (cp -al): what is written here stays here
        return
    if owner == "collect":
        raise RunFolderError(f"{where} holds a dataset (HDF5 episodes), which cicfw {app} would write beside and "
                             f"over; {fix}", key=key, value=str(folder))
    if owner is not None:
        raise RunFolderError(f"{where} holds the outputs of cicfw {owner} ({_listed(entries)}), which cicfw {app} "
                             f"would write over; {fix}", key=key, value=str(folder))
    claim_outside_runs(folder, app, key)  # <train run>/checkpoints: that run's files, not files of no app
    if app == "reproduce" and (folder / REPRODUCE_LOG).is_file():
        entries = [n for n in entries if n != REPRODUCE_LOG]  # its own log, appended to (a run stopped early)
    if not entries or foreign_ok:
        return
    raise RunFolderError(f"{where} holds files that no cicfw app wrote ({_listed(entries)}), which cicfw {app} "
                         f"would write over; {fix}", key=key, value=str(folder))


#: the job names of cicfw's apps (``conf/<app>.yaml``) and the records' owners (``RECORDS``): an enclosing
#: folder of another Hydra program is no cicfw run
CICFW_APPS = ("train", "evaluate", "collect", "diagnose", "export", "reproduce", "report")


def enclosing_run(folder: str | Path, *, include_self: bool = False) -> tuple[Path, str] | None:
    """The nearest folder above ``folder`` (or ``folder`` itself with ``include_self``), through symlinks,
    that is the run or results folder of a cicfw app other than a dataset's: (that folder, its app), or None.
    ``folder`` itself is judged as ``folder_owner`` judges an output folder; a folder above it only by records
    no other tool leaves (``_run_above``): a project or home folder holding a ``train.log`` beside
    ``checkpoints/``, or some tool's ``report.json``, is no cicfw run to write around."""
    path = Path(os.path.realpath(Path(folder).expanduser()))
    if include_self:
        owner = folder_owner(path)
        if owner is not None and owner != "collect" and _job_app(owner) in CICFW_APPS \
                and (owner != "reproduce" or _run_above(path) == "reproduce"):
            return path, owner
    for p in path.parents:
        owner = _run_above(p)
        if owner is not None:
            return p, owner
    return None


def _run_above(folder: Path) -> str | None:
    """The cicfw app ``folder`` is the run of, from a record only cicfw leaves: Hydra's record naming a cicfw
    app's job, a reproduction's manifest or its cell tree (``cells/<row>/seed<k>``), a training run's data
    record beside its outputs (``TRAIN_API_OUTPUTS``); None otherwise."""
    job = _hydra_job(folder)
    if job is not None:
        job = _job_app(job)
        return job if job in CICFW_APPS and job != "collect" else None
    if is_reproduction_results(folder):
        return "reproduce"
    return "train" if _trained_through_api(folder) else None


#: the folders cicfw itself makes inside another app's run, which the app writing them claims again (to resume
#: them): (the enclosing run's app, the folder's path below it, that app). The evaluation after training's
#: ``<run>/evaluate``, resumed with ``cicfw evaluate hydra.run.dir=<run>/evaluate``
NESTED_RUNS = (("train", "evaluate", "evaluate"),)


def claim_outside_runs(folder: str | Path, app: str, key: str, found: tuple[Path, str] | None = None) -> None:
    """One ``RunFolderError`` naming ``key`` when ``folder`` lies inside another cicfw app's run or results
    folder (``enclosing_run``): what ``app`` writes there would read as part of that run (a dataset among a
    training run's checkpoints, HDF5 files among a reproduction's cells, an evaluation in ``<run>/csv``).
    A run of ``app`` itself (a sweep's job folders) and the ``NESTED_RUNS`` pass. ``found``: ``enclosing_run``'s
    answer where the caller has it already."""
    found = found or enclosing_run(folder)
    if found is None or found[1] == app:
        return
    run, owner = found
    below = Path(os.path.realpath(Path(folder).expanduser())).relative_to(run).as_posix()
    if (owner, below, app) in NESTED_RUNS:
        return
    what = "results folder" if owner == "reproduce" else "run"
    raise RunFolderError(f"{key}={str(folder)!r} lies inside the cicfw {owner} {what} {str(run)!r}, among whose files "
                         f"cicfw {app} would write; give a folder outside it ({key}=<new folder>)",
                         key=key, value=str(folder))
