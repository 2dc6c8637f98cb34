"""The run folder checked before Hydra creates it: a read-only folder, a name longer than the
filesystem allows (``hydra.run.dir=<300 characters>``, ``hydra.job.name=...``) or a path through a
file is one line (``cicfw: error: ...``, exit status 2), not a traceback from inside Hydra.

``RunFolderCheck`` is a Hydra callback (``hydra.callbacks.run_folder`` in conf/train.yaml and
conf/evaluate.yaml); ``check_run_folder`` is the check itself.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any, Sequence

from hydra.experimental.callback import Callback


class RunFolderError(ValueError):
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


def check_run_folder(folder: str | Path, key: str = "hydra.run.dir", files: Sequence[tuple[str, str]] = ()) -> None:
    """Create ``folder`` (if needed) and a file in it, or raise one ``RunFolderError`` naming ``key``.

    ``files``: (key, file name) pairs the run will create there (the job's log), checked for length."""
    folder = Path(folder)
    _check_names([(key, part) for part in folder.parts] + list(files), name_max(folder))
    what = "write" if _exists(folder) else "create"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe = folder / f".cicfw-probe-{os.getpid()}"
        os.close(os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
        os.unlink(probe)
    except OSError as err:
        raise RunFolderError(f"cannot {what} the run folder {folder} ({err.strerror or err}); give a folder you "
                             f"can write: {key}=<folder>") from None


class RunFolderCheck(Callback):
    """Hydra callback: the run folder (or the sweep folder) checked before the job starts."""

    def on_run_start(self, config: Any, **kwargs: Any) -> None:
        job = str(config.hydra.job.name)
        self._check(config.hydra.run.dir, "hydra.run.dir", [("hydra.job.name", f"{job}.log")])

    def on_multirun_start(self, config: Any, **kwargs: Any) -> None:
        job = str(config.hydra.job.name)
        self._check(config.hydra.sweep.dir, "hydra.sweep.dir", [("hydra.job.name", f"{job}.log")])

    @staticmethod
    def _check(folder: Any, key: str, files: Sequence[tuple[str, str]]) -> None:
        try:
            check_run_folder(str(folder), key, files)
        except RunFolderError as err:
            print(f"cicfw: error: {err}", file=sys.stderr)
            sys.exit(2)
