"""Atomic file writes, shared by every layer: a temporary file beside the final name, then a rename, so a
reader (or a full disk, or a kill) never finds half a file under the final name; ``write_together``
does it for a group of files (an episode's parts, a model and its sidecar): all or none. Files get the mode a
plain ``open`` gives (0666 less the umask), not ``mkstemp``'s owner-only 0600: a shared results folder,
dataset or run folder stays readable by colleagues. ``writable_folder``: an app's output folder made and
checked before anything is written there. It imports nothing from cicfw but its errors (the bottom layer,
beside the registry).
"""
from __future__ import annotations

import contextlib
import errno
import os
import re
import secrets
import shutil
import stat
from pathlib import Path
from typing import Callable, Iterable, Iterator, Mapping

from cicfw.core.errors import ConfigError


def _temp_name(path: Path, suffix: str, pid: int | None = None) -> Path:
    """``.<name>.<pid>-<random><suffix>`` beside ``path``: hidden, and telling which process left it."""
    return path.with_name(f".{path.name}.{os.getpid() if pid is None else pid}-{secrets.token_hex(4)}{suffix}")


def temp_name_bytes(name: str, suffix: str = ".tmp", pid: int | None = None) -> int:
    """How long (bytes) the temporary name of a file ``name`` is while process ``pid`` (this one) writes it:
    what the filesystem's name limit must take, checked before the work that writes it."""
    return len(os.fsencode(_temp_name(Path(name), suffix, pid).name))


#: ``_temp_name``'s files: the writer's pid is the first group
TEMP_NAME = re.compile(r"^\..+\.(\d+)-[0-9a-f]{8}\.[a-z]+$")


def running(pid: int) -> bool:
    """Whether a process ``pid`` runs on this machine (one owned by another user counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale_temps(folder: str | os.PathLike) -> list[Path]:
    """The temporary files (``_temp_name``'s) under ``folder`` whose writer no longer runs, removed: a
    process killed while writing (SIGKILL, a lost node) cannot clean up after itself. Only for a folder
    the caller holds (its lock), so that no writer on another machine is still filling one. Returns them."""
    stale = [p for p in Path(folder).rglob(".*") if p.is_file() and (m := TEMP_NAME.match(p.name))
             and int(m.group(1)) != os.getpid() and not running(int(m.group(1)))]
    for p in stale:
        p.unlink(missing_ok=True)
    return stale


def temp_beside(path: Path, suffix: str = ".tmp") -> tuple[int, Path]:
    """A new, empty temporary file in ``path``'s folder (``.<name>.<pid>-<random><suffix>``), open for
    writing, with the umask's mode. Returns its descriptor and path."""
    for _ in range(100):
        tmp = _temp_name(path, suffix)
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
def _about(path: Path) -> Iterator[None]:
    """An OSError raised inside is raised again as the same error (same errno, same subclass) about
    ``path``, the final name the caller knows (``err.filename``), not a temporary one."""
    try:
        yield
    except OSError as err:
        raise OSError(err.errno, err.strerror or str(err), str(path)) from err


def publish_new(tmp: Path, path: Path) -> None:
    """Give the written file ``tmp`` the name ``path`` only where no file has it: a hard link, which fails
    with ``FileExistsError`` when another process made ``path`` meanwhile (a rename would replace it), then
    the temporary name removed. Where the filesystem has no hard links, an exclusive create of ``path``
    stands for the check before the rename."""
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise
    except OSError as err:
        if err.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EMLINK, errno.ENOSYS):
            raise
        os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))  # FileExistsError if it is there
        try:
            os.replace(tmp, path)
        except BaseException:  # the empty file made above is no output: left, a rerun would find it in the way
            with contextlib.suppress(FileNotFoundError):
                os.unlink(path)
            raise
        return
    tmp.unlink(missing_ok=True)


def _keep_mode(tmp: Path, path: Path) -> None:
    """``tmp``, about to replace ``path``, takes ``path``'s permission bits: a report shared as 0664 stays
    readable by its group when it is rewritten under a umask of 077."""
    try:
        mode = stat.S_IMODE(os.stat(path).st_mode)
    except FileNotFoundError:
        return
    os.chmod(tmp, mode)


def write_together(files: Mapping[Path, bytes | memoryview] | Iterable[tuple[Path, bytes | memoryview]], *,
                   fsync: bool = False, suffix: str = ".tmp",
                   before_rename: Callable[[], None] | None = None, new: Iterable[Path] = ()) -> None:
    """Write each file under a temporary name beside it (``temp_beside``), then, all written and
    ``before_rename`` (if given) passed, rename them to their final names in order: on any failure
    before that, every temporary file is removed and no final name touched. ``files`` may be pairs made
    as they are written (one file's bytes in memory at a time). ``fsync``: each file reaches the disk
    before any is renamed. An OSError while writing or renaming names the final path (``err.filename``).
    ``new``: final names that were free when the caller checked its output: each is only created, never
    replaced (``publish_new``), so a file another process wrote there since raises ``FileExistsError``,
    and the names this call gave its files before that are removed again (those it created)."""
    temps: list[tuple[Path, Path]] = []  # (temporary, final)
    new = {os.path.abspath(p) for p in new}
    created: list[tuple[Path, tuple[int, int]]] = []  # (final, its file's identity) published by publish_new
    try:
        for path, data in files.items() if isinstance(files, Mapping) else files:
            with _about(path):
                fd, tmp = temp_beside(path, suffix)
                temps.append((tmp, path))
                try:
                    write_all(fd, data)
                    if fsync:
                        os.fsync(fd)
                finally:
                    os.close(fd)
        if before_rename is not None:
            before_rename()
        for tmp, path in temps:
            with _about(path):
                if os.path.abspath(path) in new:
                    st = os.stat(tmp)
                    publish_new(tmp, path)
                    created.append((path, (st.st_dev, st.st_ino)))
                else:
                    _keep_mode(tmp, path)
                    os.replace(tmp, path)
    except BaseException:
        for tmp, _ in temps:
            tmp.unlink(missing_ok=True)
        for path, ident in created:  # all or none: only this call's own files, not one written over them
            with contextlib.suppress(OSError):
                st = os.stat(path)
                if (st.st_dev, st.st_ino) == ident:
                    path.unlink()
        raise


#: the probe ``writable_folder`` writes and removes (a folder holding one is no one's output)
PROBE_PREFIX = ".cicfw-probe-"


def writable_folder(path: str | os.PathLike, key: str, accepted: str, what: str = "the folder",
                    value: object = None) -> Path:
    """``path`` made (with its parents) and a file written and removed there, before an app writes anything:
    a file in the way, or a folder that cannot be made or written, is one ``ConfigError`` naming ``key``
    and ``value`` (the path unless the setting that chose it says otherwise), why, and ``accepted``.
    ``what`` names the folder in the message ("the run folder")."""
    path = Path(path)
    verb = "write" if os.path.isdir(path) else "create"  # os.path's: False, not an error, for a name too long
    try:
        if verb == "create" and os.path.lexists(path):
            raise NotADirectoryError(errno.ENOTDIR, "a file, not a folder")
        path.mkdir(parents=True, exist_ok=True)
        probe = path / f"{PROBE_PREFIX}{os.getpid()}-{secrets.token_hex(4)}"
        os.close(os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
        os.unlink(probe)
        return path
    except OSError as err:
        why = err.strerror or str(err)
    shown = str(path) if value is None else value
    got = "" if value is None else f", got {value}"
    raise ConfigError(key, shown, accepted, f"cannot {verb} {what} {path} ({why}); {key} must be {accepted}{got}")


def atomic_write(path: str | os.PathLike, data: str | bytes | memoryview) -> None:
    """Write ``data`` (text as UTF-8) to ``path`` through a temporary file beside it, then rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_together({path: data.encode() if isinstance(data, str) else data})


def unshare(path: str | Path) -> bool:
    """Give ``path``, a regular file hard-linked elsewhere (a ``cp -al`` copy of a run), a copy of its own, so that
    what is rewritten or appended to in place there stays out of the other folder; whether it did."""
    path = Path(path)
    try:
        info = os.lstat(path)
    except OSError:  # gone meanwhile: nothing to share
        return False
    if not (stat.S_ISREG(info.st_mode) and info.st_nlink > 1):
        return False
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")
    shutil.copy2(path, tmp)
    os.replace(tmp, path)
    return True


def unshare_links(folder: str | Path) -> list[Path]:
    """``unshare`` each file under ``folder`` (Hydra's ``.hydra`` records and job log, an episode log, a
    reproduction's logs) but lock files, whose lock is on the file, which a copy would not hold. Returns the files
    copied."""
    return [path for dirpath, _, names in os.walk(folder) for name in names if not name.endswith(".lock")
            for path in [Path(dirpath) / name] if unshare(path)]
