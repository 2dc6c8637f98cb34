"""Writing files with nothing half-written: bytes built in memory (``cil_hdf5.file_bytes``), written
under temporary names unique to the process, then renamed (``cicfw.core.files.write_together``); a full disk
is one clear error."""
from __future__ import annotations

import errno
import json
import shutil
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

from cicfw.collect.errors import CollectError, DiskFullError
from cicfw.core.files import write_together


def disk_error(err: OSError, path: Path, what: str) -> CollectError:
    """A failed write as one clear error: DiskFullError on ENOSPC / EDQUOT (with the free space), else
    a CollectError naming the file."""
    if err.errno in (errno.ENOSPC, errno.EDQUOT):
        free = shutil.disk_usage(path.parent).free  # (not _free_bytes: the truth, whatever the check said)
        return DiskFullError(f"no space left on the device of {path.parent} while writing {what} "
                             f"({free / 1e6:.1f} MB free); free some space or collect into another folder "
                             f"(out_dir=...), then rerun to resume", key="out_dir", value=path.parent)
    return CollectError(f"could not write {path} ({err.strerror or err}); check the folder and rerun to resume")


def write_files(files: Mapping[Path, bytes] | Iterable[tuple[Path, bytes]], suffix: str = ".part",
                before_rename: Callable[[], None] | None = None) -> None:
    """``cicfw.core.files.write_together``, fsynced: every file gets its final name or none does. A failed
    write is one CollectError naming the file (DiskFullError on ENOSPC)."""
    try:
        write_together(files, fsync=True, suffix=suffix, before_rename=before_rename)
    except OSError as err:
        if err.filename is None:  # not the write's own (a caller's ``files`` or ``before_rename``)
            raise
        path = Path(err.filename)
        raise disk_error(err, path, path.name) from None


def write_json(path: Path, obj: Any) -> None:
    """Write JSON atomically (temporary name unique to the process, then rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    write_files({path: json.dumps(obj, indent=1, sort_keys=True).encode()}, ".tmp")


def _free_bytes(path: Path) -> int:
    return shutil.disk_usage(path).free


def check_free_space(out_dir: Path, need: int, what: str) -> None:
    free = _free_bytes(out_dir)
    if free < need:
        raise DiskFullError(f"not enough free space in {out_dir}: {what} needs ~{need / 1e6:.1f} MB, "
                            f"{free / 1e6:.1f} MB free; free some space or collect into another folder (out_dir=...)",
                            key="out_dir", value=out_dir)
