"""One collector per folder: an exclusive ``flock`` on ``<folder>/.collect.lock`` that names its holder."""
from __future__ import annotations

import json
import logging
import os
import socket
import time
from pathlib import Path
from typing import Any

from cicfw.collection.errors import CollectError, FolderLockedError
from cicfw.collection.writing import disk_error

log = logging.getLogger(__name__)

LOCK_NAME = ".collect.lock"


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
            raise disk_error(err, self.path, "the lock file") from None

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
