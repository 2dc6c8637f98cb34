"""One ``reproduce`` run per results folder: a lock file (``reproduce.lock``) that names its holder, held
with ``flock`` for the run's life, and taken over with a warning when its holder is gone."""
from __future__ import annotations

import json
import logging
import os
import socket
import sys
import time
from pathlib import Path
from typing import Any, Mapping

log = logging.getLogger("cicfw.reproduce")

LOCK_FILE = "reproduce.lock"


class FolderInUse(ValueError):
    """Another run holds the results folder (or its lock kept changing): one line naming the holder."""


class ResultsLock:
    """One ``reproduce`` run per results folder: ``<results_dir>/reproduce.lock`` names the holder (pid, host,
    start time, command) and is held with an exclusive ``flock`` for the run's life, removed when it ends.
    Another run on the folder is refused in one line naming the holder. A lock whose holder is gone (the
    flock is free, and its pid on this host is dead or younger than the lock: a killed run) is stale and
    taken over with a warning; a record from another host is never taken over (its pid cannot be checked
    here): the message says to delete the file if that run is gone."""

    def __init__(self, results_dir: Path) -> None:
        self.dir = Path(results_dir)
        self.path = self.dir / LOCK_FILE
        self.fd: int | None = None
        self.made_dir = False

    def _in_use(self, holder: Mapping[str, Any], certain: bool) -> FolderInUse:
        who = (f"pid {holder.get('pid', '?')} on host {holder.get('host', '?')}, started "
               f"{holder.get('started', '?')}")
        tail = ("" if certain else f"; if it is no longer running, delete {str(self.path)!r}")
        return FolderInUse(f"results folder {str(self.dir)!r} is in use by another reproduce run ({who}): one run "
                              f"per folder; wait for it to finish, or give another results_dir=<path>{tail}")

    def acquire(self) -> "ResultsLock":
        import fcntl

        self.made_dir = not self.dir.exists()
        self.dir.mkdir(parents=True, exist_ok=True)
        for _ in range(20):
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:  # a live run holds it
                holder = _read_lock(fd)
                os.close(fd)
                raise self._in_use(holder, certain=True) from None
            try:  # the file we locked is still the one at the path (a finishing holder unlinks it)
                same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if not same:
                os.close(fd)
                continue
            holder = _read_lock(fd)
            if holder:
                if holder.get("host") != socket.gethostname() or _holder_alive(holder):
                    os.close(fd)
                    raise self._in_use(holder, certain=False)
                log.warning("results folder %s: taking over the stale lock of pid %s on %s (started %s), which is "
                            "no longer running", self.dir, holder.get("pid"), holder.get("host"), holder.get("started"))
            now = time.time()
            record = {"pid": os.getpid(), "host": socket.gethostname(),
                      "started": time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(now)), "started_epoch": now,
                      "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]])[:500]}
            os.ftruncate(fd, 0)
            os.pwrite(fd, json.dumps(record).encode(), 0)
            self.fd = fd
            return self
        raise FolderInUse(f"could not take the lock {str(self.path)!r} (it kept changing); try again")

    def release(self) -> None:
        if self.fd is None:
            return
        try:
            self.path.unlink(missing_ok=True)  # while still holding it: a waiting run then retries the new file
        finally:
            os.close(self.fd)
            self.fd = None
        if self.made_dir:
            try:
                self.dir.rmdir()  # a folder this run made and nothing was written into
            except OSError:
                pass


def _read_lock(fd: int) -> dict[str, Any]:
    try:
        data = os.pread(fd, 65536, 0)
        return json.loads(data) if data.strip() else {}
    except (OSError, ValueError):
        return {"pid": "?", "host": "?", "started": "? (an unreadable lock file)"}


def _holder_alive(holder: Mapping[str, Any]) -> bool:
    """Whether the lock's pid (on this host) is a live process that is not younger than the lock."""
    try:
        pid = int(holder.get("pid"))
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass  # alive, someone else's
    except (TypeError, ValueError):
        return False
    started = holder.get("started_epoch")
    try:  # a pid reused after the holder died (a reboot, a container) started after the lock was taken
        ticks = int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19])
        btime = next(int(ln.split()[1]) for ln in Path("/proc/stat").read_text().splitlines() if ln.startswith("btime"))
        if started is not None and btime + ticks / os.sysconf("SC_CLK_TCK") > float(started) + 1.0:
            return False
    except (OSError, ValueError, IndexError, StopIteration):
        pass
    return True
