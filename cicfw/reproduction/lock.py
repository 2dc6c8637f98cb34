"""One ``reproduce`` run per results folder: the project's ``FolderLock`` on ``<results_dir>/reproduce.lock``,
in the reproduction's words."""
from __future__ import annotations

import logging
from typing import Any, Mapping

from cicfw.core import locks

LOCK_FILE = "reproduce.lock"


class ResultsLock(locks.FolderLock):
    """``<results_dir>/reproduce.lock`` names the holder (pid, host, start time, command) for the run's life.
    Another run on the folder is refused in one line naming the holder. A record whose holder is gone (its
    pid on this host is dead, or younger than the record: a killed run) is taken over with a warning; one
    from another host never is (its pid cannot be checked here): the message says to delete the file."""

    lock_name = LOCK_FILE
    check_pid = True
    log = logging.getLogger("cicfw.reproduce")

    def busy(self, holder: Mapping[str, Any], waited: float, certain: bool) -> locks.FolderBusy:
        who = (f"pid {holder.get('pid', '?')} on host {holder.get('host', '?')}, started "
               f"{holder.get('started', '?')}")
        tail = ("" if certain else f"; if it is no longer running, delete {str(self.path)!r}")
        return locks.FolderBusy(f"results folder {str(self.folder)!r} is in use by another reproduce run ({who}): "
                                f"one run per folder; wait for it to finish, or give another results_dir=<path>{tail}",
                                key="results_dir", value=self.folder)
