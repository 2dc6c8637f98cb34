"""One process per folder: ``FolderLock``, an exclusive ``flock`` on a lock file that names its holder.

Written on ``fcntl.flock``, not the ``filelock`` library: the lock file itself carries the holder's record
(pid, host, start, command) that a refusal names and a stale-lock takeover checks, which filelock lacks.

The file exists only while a run holds it: the holder unlinks it before letting go, and a process that
gets the flock checks that its file is still the one at the path (it may have waited on a file since
unlinked) and otherwise opens the path again, so two processes never hold two files at one path. A
record found under a free flock was left by a holder that died: it is taken over with a warning.
"""
from __future__ import annotations

import errno
import json
import logging
import os
import socket
import sys
import time
from pathlib import Path
from typing import Any, Mapping

from cicfw.core.errors import CicfwError
from cicfw.core.files import running

try:
    import fcntl
except ImportError:  # Windows: no flock
    fcntl = None

#: how often a waiting process tries the lock again (seconds)
POLL_S = 0.2
#: inode changes in a row (holders finishing one after another) before giving up
MAX_RETRIES = 20


class FolderBusy(CicfwError):
    """Another process holds the folder; the message names it."""


def flock_available() -> bool:
    """Whether this platform has ``flock`` (not Windows)."""
    return fcntl is not None


def describe_holder(holder: Mapping[str, Any]) -> str:
    """``pid 12 on host, started 2024-01-01 10:00:00 (what)``: the holder as refusals name it."""
    if not holder.get("pid"):
        return "a process that has not recorded itself yet"
    what = f" ({holder['what']})" if holder.get("what") else ""
    return f"pid {holder['pid']} on {holder.get('host', '?')}, started {holder.get('started', '?')}{what}"


def holder_name(holder: Mapping[str, Any]) -> str:
    """What holds a lock, as its record names it: its command line quoted (``report.py R1``), else "another
    process" (a record without one, or not written yet), never a guess from the lock's name."""
    command = str(holder.get("command") or "").strip()
    return f"`{command}`" if command else "another process"


class FolderLock:
    """An exclusive ``flock`` on ``<folder>/<lock_name>`` for one run, its holder recorded in the file.

    ``wait``: seconds to wait for another holder (0: refuse at once; None: as long as it takes); ``info``:
    extra keys for the record (``what``: shown in refusals). Use ``with FolderLock(folder):`` or
    ``acquire()``/``release()``. Subclasses word their errors (``busy``, ``unusable``) and set the class
    attributes below.
    """

    lock_name = ".lock"
    #: refuse a record left under a free flock unless its pid on this host is gone (another host's is
    #: never taken over: its pid cannot be checked here); False: the free flock alone decides
    check_pid = False
    #: what the waiting message says the holder is doing, and its level
    activity = "holds it"
    wait_level = logging.WARNING
    log = logging.getLogger(__name__)

    def __init__(self, folder: str | Path, wait: float | None = 0.0, info: Mapping[str, Any] | None = None) -> None:
        self.folder, self.wait, self.info = Path(folder), wait, dict(info or {})
        self.path = self.folder / self.lock_name
        self.fd: int | None = None
        self.since = 0.0  # when this process took the lock (epoch seconds)
        self.made_folder = False

    # ---- the words: override to raise a caller's own errors ----------------------------------------
    def busy(self, holder: Mapping[str, Any], waited: float, certain: bool) -> Exception:
        """The refusal when another process holds the folder (``certain``: its flock is held; else its
        record under a free flock could not be shown stale)."""
        after = f" after waiting {waited:.0f} s" if self.wait else ""
        tail = "" if certain else f"; if it is no longer running, delete {str(self.path)!r}"
        return FolderBusy(f"{self.folder} is in use by another process ({describe_holder(holder)}){after}; wait "
                          f"for it to finish, or use another folder{tail}", value=self.folder)

    def unusable(self, err: OSError, step: str) -> Exception:
        """The error when the lock cannot be used at all (``step``: ``open``, ``lock`` or ``record``)."""
        return err

    def doing(self, holder: Mapping[str, Any]) -> str:
        """What the waiting message says ``holder`` is doing with the folder (``activity``, unless a
        subclass tells its holders apart by their records)."""
        return self.activity

    # ---- taking and giving back --------------------------------------------------------------------
    def acquire(self) -> "FolderLock":
        """Take the lock (waiting as ``wait`` says) and record this process as its holder."""
        t0, said, retries = time.monotonic(), False, 0
        while True:
            fd = self._open()
            if self._flock(fd):
                if self._is_current(fd):
                    break
                os.close(fd)  # its holder unlinked it while this process waited: the path has a new file
                retries += 1
                if retries < MAX_RETRIES:
                    continue
                holder = {}
            else:
                holder = read_record(fd)
                os.close(fd)
            waited = time.monotonic() - t0
            if self.wait is not None and waited >= self.wait:
                raise self.busy(holder, waited, certain=True)
            if not said:
                self.log.log(self.wait_level, "waiting for %s: another process %s (%s)", self.folder,
                             self.doing(holder), describe_holder(holder))
                said = True
            time.sleep(POLL_S)
        self._take_over(fd)
        self.fd, self.since = fd, time.time()
        self.update()
        return self

    def update(self, **extra: Any) -> None:
        """Record the holder (and ``extra``, e.g. worker pids) in the lock file."""
        self.info.update(extra)
        record = {"pid": os.getpid(), "host": socket.gethostname(),
                  "started": time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(self.since)),
                  "started_epoch": self.since, "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]])[:500],
                  **self.info}
        try:
            os.ftruncate(self.fd, 0)
            os.pwrite(self.fd, json.dumps(record).encode(), 0)
        except OSError as err:
            self.release()
            raise self.unusable(err, "record") from None

    def release(self) -> None:
        """Remove the lock file (while still holding it) and let go; a folder the lock made, left empty,
        goes too."""
        if self.fd is None:
            return
        try:
            if self._is_current(self.fd):
                self.path.unlink()
        except OSError:
            pass  # a read-only folder keeps the file; the next holder takes it over
        finally:
            os.close(self.fd)
            self.fd = None
        if self.made_folder:
            try:
                self.folder.rmdir()
            except OSError:
                pass

    def __enter__(self) -> "FolderLock":
        return self.acquire()

    def __exit__(self, *exc: Any) -> None:
        self.release()

    # ---- steps -------------------------------------------------------------------------------------
    def _open(self) -> int:
        """The lock file's descriptor (the folder made if missing)."""
        try:
            if not self.folder.is_dir():
                self.folder.mkdir(parents=True, exist_ok=True)
                self.made_folder = True
            return os.open(self.path, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o644)
        except OSError as err:
            raise self.unusable(err, "open") from None

    def _flock(self, fd: int) -> bool:
        """Try the exclusive flock without blocking: True when taken, False when another holds it."""
        if fcntl is None:
            os.close(fd)
            raise self.unusable(OSError(errno.ENOSYS, "this platform has no flock"), "lock")
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return True
        except BlockingIOError:
            return False
        except OSError as err:  # e.g. a file system without flock
            os.close(fd)
            raise self.unusable(err, "lock") from None

    def _is_current(self, fd: int) -> bool:
        """Whether ``fd`` is still the file at the path (a finishing holder unlinks it)."""
        try:
            return os.fstat(fd).st_ino == os.stat(self.path).st_ino
        except FileNotFoundError:
            return False

    def _take_over(self, fd: int) -> None:
        """A record under a free flock: a holder that died. Warn and take it over, or (``check_pid``)
        refuse when its pid may still run."""
        holder = read_record(fd)
        if not holder:
            return
        if self.check_pid and (holder.get("host") != socket.gethostname() or pid_alive(holder)):
            os.close(fd)
            raise self.busy(holder, 0.0, certain=False)
        self.log.warning("%s: taking over the stale lock of pid %s on %s (started %s), which is no longer running",
                         self.folder, holder.get("pid", "?"), holder.get("host", "?"), holder.get("started", "?"))


def read_record(fd: int) -> dict[str, Any]:
    """The holder's record in the lock file; {} for an empty file (nobody recorded)."""
    try:
        data = os.pread(fd, 65536, 0)
        record = json.loads(data) if data.strip() else {}
    except (OSError, ValueError):
        return {"pid": "?", "host": "?", "started": "? (an unreadable lock file)"}
    return record if isinstance(record, dict) else {"pid": record}  # a bare pid: an older cicfw's


def pid_alive(holder: Mapping[str, Any]) -> bool:
    """Whether the record's pid (on this host) is a live process that is not younger than the record."""
    try:
        pid = int(holder.get("pid"))
    except (TypeError, ValueError):
        return False
    if not running(pid):
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


def live_holder(path: str | Path) -> tuple[dict[str, Any], bool] | None:
    """The holder of the lock file at ``path`` while it may still run, read without taking the lock or
    creating the file: (its record, certain), ``certain`` when its pid on this host is alive (or it holds
    the flock before recording itself), not when the record is another host's, whose pid cannot be checked
    here or whose recorded start lies in the future; None when there is no lock file or its holder is gone (a
    stale lock)."""
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_CLOEXEC", 0))
    except OSError:
        return None
    try:
        holder = read_record(fd)
        if not holder:  # opened, not yet recorded: live while its flock is held
            if fcntl is None:
                return None
            try:
                fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
                return None
            except OSError:
                return {}, True
    finally:
        os.close(fd)
    if holder.get("host") != socket.gethostname():
        return holder, False
    if not pid_alive(holder):
        return None
    started = holder.get("started_epoch")  # a start in the future: a clock set back, or a record not cicfw's
    return holder, not (isinstance(started, (int, float)) and started > time.time() + 60)
