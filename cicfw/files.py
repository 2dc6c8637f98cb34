"""Atomic file writes, shared by every layer: a temporary file beside the final name, then a rename, so a
reader (or a full disk, or a kill) never finds half a file under the final name. Files get the mode a
plain ``open`` gives (0666 less the umask), not ``mkstemp``'s owner-only 0600: a shared results folder,
dataset or run folder stays readable by colleagues. It imports nothing from cicfw (the bottom layer,
beside the registry).
"""
from __future__ import annotations

import contextlib
import os
import secrets
from pathlib import Path
from typing import Iterator


def temp_beside(path: Path) -> tuple[int, Path]:
    """A new, empty temporary file in ``path``'s folder (``.<name>.<random>.tmp``), open for writing,
    with the umask's mode. Returns its descriptor and path."""
    for _ in range(100):
        tmp = path.parent / f".{path.name}.{secrets.token_hex(4)}.tmp"
        try:
            return os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0), 0o666), tmp
        except FileExistsError:
            continue
    raise FileExistsError(f"no free temporary name beside {path}")


def write_all(fd: int, data: bytes | memoryview) -> None:
    """``os.write`` until every byte is written (one call may write fewer)."""
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


@contextlib.contextmanager
def replacing(path: str | os.PathLike) -> Iterator[Path]:
    """For writers that need a file name (h5py, savefig to a path): yields the temporary file's path,
    then renames it to ``path``; on any error the temporary file is removed and ``path`` is untouched."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = temp_beside(path)
    os.close(fd)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def atomic_write(path: str | os.PathLike, data: str | bytes) -> None:
    """Write ``data`` (text as UTF-8) to ``path`` through a temporary file beside it, then rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = temp_beside(path)
    try:
        try:
            write_all(fd, data.encode() if isinstance(data, str) else data)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
