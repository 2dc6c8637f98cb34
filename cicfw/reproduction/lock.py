"""One ``reproduce`` run per results folder (and per ``publish_dir``): the project's ``FolderLock`` on
``<folder>/reproduce.lock``, in the reproduction's words."""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Mapping

from cicfw.core import locks

LOCK_FILE = "reproduce.lock"


class ResultsLock(locks.FolderLock):
    """``<results_dir>/reproduce.lock`` names the holder (pid, host, start time, command) for the run's life.
    Another run on the folder is refused in one line naming the holder (the command its record names: a
    reproduce run, or ``cicfw report`` writing the folder). A record whose holder is gone (its
    pid on this host is dead, or younger than the record: a killed run) is taken over with a warning; one
    from another host never is (its pid cannot be checked here): the message says to delete the file."""

    lock_name = LOCK_FILE
    check_pid = True
    log = logging.getLogger("cicfw.reproduce")

    def __init__(self, folder: str | Path, key: str = "results_dir", **kwargs: Any) -> None:
        super().__init__(folder, **kwargs)
        self.key = key  # the option that named the folder: the refusal names it

    def busy(self, holder: Mapping[str, Any], waited: float, certain: bool) -> locks.FolderBusy:
        who = (f"pid {holder.get('pid', '?')} on host {holder.get('host', '?')}, started "
               f"{holder.get('started', '?')}")
        tail = ("" if certain else f"; if it is no longer running, delete {str(self.path)!r}")
        what = "results folder" if self.key == "results_dir" else self.key
        return locks.FolderBusy(f"{what} {str(self.folder)!r} is in use by {locks.holder_name(holder)} ({who}): one "
                                f"run per folder; wait for it to finish, or give another {self.key}=<path>{tail}",
                                key=self.key, value=self.folder)


class RunLocks:
    """The folders one reproduce run writes, held for its whole life: its results folder and its ``publish_dir``
    (which every cell's report is copied into), so no other run takes either while it runs. Taken in that
    order (the first refusal gives back what was taken), given back together."""

    def __init__(self, results_dir: str | Path, publish_dir: str | Path | None = None,
                 publish_key: str = "publish_dir") -> None:
        self.folders = [(Path(results_dir), "results_dir")]
        if publish_dir:
            self.folders.append((Path(publish_dir), publish_key))  # the option that named it (cicfw report: --publish)
        self.held: list[ResultsLock] = []

    def acquire(self) -> "RunLocks":
        try:
            for folder, key in self.folders:
                self.held.append(ResultsLock(folder, key=key).acquire())
        except BaseException:
            self.release()
            raise
        return self

    def release(self) -> None:
        while self.held:
            self.held.pop().release()
