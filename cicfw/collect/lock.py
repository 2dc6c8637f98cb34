"""One collector per folder: the project's ``FolderLock`` on ``<folder>/.collect.lock``, in the collection's words;
and one collect run per Hydra run folder (``CollectRunFolderCheck``)."""
from __future__ import annotations

import logging
from typing import Any, Mapping

from cicfw.core import locks
from cicfw.collect.errors import CollectError, FolderLockedError
from cicfw.collect.writing import disk_error
from cicfw.core.run_folder import AppFolderLock, LockedRunFolderCheck

LOCK_NAME = ".collect.lock"
#: the key a holder that only reads the folder (``cicfw collect --verify``) sets in its record: another
#: collector waits for it as for a collector, and is told that the folder is being checked, not written
READS_ONLY = "reads_only"


class FolderLock(locks.FolderLock):
    """``FolderLock(folder, wait, {"what": ...})``: the collection's lock; ``update(workers=[...])`` records
    its worker pids. A second collector waits ``wait`` seconds (None: as long as it takes), then stops."""

    lock_name = LOCK_NAME
    activity = "is collecting into it"
    log = logging.getLogger(__name__)

    def doing(self, holder: Mapping[str, Any]) -> str:
        return "is verifying it (reading only)" if holder.get(READS_ONLY) else self.activity

    def busy(self, holder: Mapping[str, Any], waited: float, certain: bool) -> Exception:
        after = f" after waiting {waited:.0f} s" if self.wait else ""
        what = "being verified (read only)" if holder.get(READS_ONLY) else "being collected into"
        return FolderLockedError(f"{self.folder} is {what} by another process "
                                 f"({locks.describe_holder(holder)}){after}; wait for it to finish (lock_wait=null "
                                 f"waits), or collect into another folder", key="out_dir", value=self.folder)

    def unusable(self, err: OSError, step: str) -> Exception:
        if step == "record":
            return disk_error(err, self.path, "the lock file")
        if step == "lock":
            return CollectError(f"cannot lock the output folder {self.folder} ({err.strerror}); its file system "
                                f"does not support flock: collect into a local folder")
        return CollectError(f"cannot write to the output folder {self.folder} ({err.strerror}); give a writable "
                            f"out_dir")


#: the lock a collect run holds on its Hydra run folder: not ``LOCK_NAME``, which the engine takes on
#: ``out_dir``, so that ``out_dir=hydra.run.dir`` does not make the run wait on its own lock
RUN_LOCK_NAME = ".collect-run.lock"


class CollectRunFolderCheck(LockedRunFolderCheck):
    """Hydra callback (conf/collect.yaml): ``LockedRunFolderCheck`` with the run folder's own lock
    (``RUN_LOCK_NAME``): two collect runs into one ``hydra.run.dir`` (whatever their ``out_dir``) never both
    write its ``.hydra`` record; the second is one line naming the first, the folder left as it is."""

    def lock(self, folder: str, config: Any) -> locks.FolderLock:
        return AppFolderLock(folder, "collect", lock_name=RUN_LOCK_NAME)
