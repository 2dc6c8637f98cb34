"""What a run trained on: the absolute data path and a fingerprint of its files, recorded in the run folder
(``<run>/data.json``) and in every checkpoint (under ``CHECKPOINT_KEY``), and compared with the data a
resume, a diagnosis or an export is given.

A record holds the path as an absolute path (``data.path`` as typed may be relative to a working directory
that is gone), the root its file names are relative to, and per HDF5 file its name, size, modification
time and SHA-256; its ``hash`` is the SHA-256 of the names, sizes and SHA-256s (16 hex digits), so the same
files in another folder have the same hash. A file reached by several paths (a symlink, a hard link) is one
entry, under the name the loader reads it by (``distinct_files``); the other paths are listed under ``links``.
Records written before then hashed every path (``HASH_OF_EVERY_PATH``): they are compared the way they were
made. Hashing stays cheap: a file whose name, size and modification time match a record given as ``known``
(the checkpoint a run resumes from, the record a diagnosis checks) keeps its recorded SHA-256, and so does a
file whose size and modification time (ns) match those ``dataset_metadata.json`` recorded with the
collection's SHA-256; only the others are read.
"""
from __future__ import annotations

import glob
import hashlib
import json
import os
import time
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

from cicfw.core.errors import CicfwError
from cicfw.core.files import atomic_write
from cicfw.data.cil_hdf5 import check_signature, find_files
from cicfw.data.frames import META_NAME, distinct_files

#: the run folder's record of its data
RECORD_FILE = "data.json"
#: the key of the record in a checkpoint
CHECKPOINT_KEY = "cicfw_data"
HASH_OF = "the distinct files' names (relative to root), sizes and SHA-256 (other paths to them: links)"
#: what a record written before links were counted once hashed: every path, a link as a file of its own
HASH_OF_EVERY_PATH = "the files' names (relative to root), sizes and SHA-256"
#: the record's key for the towns and weathers the data was collected in when training started
#: (``{"towns": [...], "weathers": [...]}``, null when the data said none): the suite's training columns
SETS_KEY = "collected_in"


class OtherData(CicfwError):
    """The data given is not the data a run recorded (another folder, or another file set)."""


def file_sha256(path: str | os.PathLike) -> str:
    """The SHA-256 of a file's bytes, read in 8 MB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(8 << 20):
            h.update(block)
    return h.hexdigest()


def absolute(path: str | os.PathLike) -> str:
    """``path`` with ``~`` expanded, made absolute against the working directory (not resolved: a link keeps
    the name the user gave it)."""
    return os.path.abspath(os.path.expanduser(str(path)))


def data_root(path: str | os.PathLike) -> Path:
    """The folder a record's file names are relative to: ``path`` itself for a folder, the folder before
    the first glob character for a glob, the file's folder for one file."""
    p = absolute(path)
    if os.path.isdir(p):
        return Path(p)
    parts = Path(p).parts
    for i, part in enumerate(parts):
        if glob.has_magic(part):
            return Path(*parts[:i])
    return Path(p).parent


def _collected_hashes(files: Iterable[Path]) -> dict[Path, str]:
    """SHA-256s the collection recorded (``dataset_metadata.json``'s ``files``) for files that are provably
    the ones it hashed: the size and modification time (ns) it recorded with the hash match the file's now. A
    file copied over another with its times kept (``cp -p``, ``rsync -a``, ``tar x``) has the other's mtime,
    and metadata written before cicfw recorded mtimes vouches for nothing: those files are hashed."""
    out: dict[Path, str] = {}
    metas: dict[Path, dict] = {}
    for f in files:
        if f.parent not in metas:
            try:
                listed = json.loads((f.parent / META_NAME).read_text()).get("files")
            except (OSError, ValueError, AttributeError):
                listed = None
            metas[f.parent] = listed if isinstance(listed, dict) else {}
        entry = metas[f.parent].get(f.name)
        if not (isinstance(entry, dict) and isinstance(entry.get("sha256"), str)
                and all(type(entry.get(k)) is int for k in ("bytes", "mtime_ns"))):
            continue
        try:
            st = f.stat()
        except OSError:
            continue
        if (st.st_size, st.st_mtime_ns) == (entry["bytes"], entry["mtime_ns"]):
            out[f] = entry["sha256"]
    return out


def files_hash(files: Sequence[Mapping[str, Any]]) -> str:
    """The fingerprint of a file list: SHA-256 of each file's name, size and SHA-256, sorted by name."""
    lines = "".join(f"{f['name']}:{f['bytes']}:{f['sha256']}\n" for f in sorted(files, key=lambda f: f["name"]))
    return hashlib.sha256(lines.encode()).hexdigest()[:16]


def _name(f: Path, root: Path) -> str:
    return Path(os.path.relpath(f, root)).as_posix()


def _entries(files: Sequence[Path], root: Path, known: Mapping[str, Any] | None) -> list[dict[str, Any]]:
    cache = {str(f.get("name")): f for f in (known or {}).get("files") or [] if isinstance(f, Mapping)}
    collected = _collected_hashes(files)
    known_sha: dict[Path, str] = {}
    for f in files:
        st, old = f.stat(), cache.get(_name(f, root))
        if old and old.get("bytes") == st.st_size and old.get("mtime_ns") == st.st_mtime_ns and old.get("sha256"):
            known_sha[f] = str(old["sha256"])
        elif f in collected:
            known_sha[f] = collected[f]
        else:
            check_signature(f)  # a file the loader refuses is named before any file is read whole
    out = []
    for f in files:
        st = f.stat()
        out.append({"name": _name(f, root), "bytes": int(st.st_size), "mtime_ns": int(st.st_mtime_ns),
                    "sha256": known_sha.get(f) or file_sha256(f)})
    return out


def record_data(path: str | os.PathLike, known: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The record of the HDF5 files ``path`` (a folder, searched recursively, or a glob) holds now, each file
    once as the loader reads it (a link to one is named under ``links``). ``known``: an earlier record whose
    SHA-256s are reused for files of the same name, size and modification time."""
    root = data_root(path)
    files, same = distinct_files(find_files(absolute(path)))
    entries = _entries(files, root, known)
    links = [{"name": _name(link, root), "same_as": _name(kept, root)} for link, kept in same]
    meta = root / META_NAME
    try:
        collect_hash = json.loads(meta.read_text()).get("config_hash") if meta.is_file() else None
    except (OSError, ValueError, AttributeError):
        collect_hash = None
    return {"path": absolute(path), "root": str(root), "hash": files_hash(entries), "hash_of": HASH_OF,
            "n_files": len(entries), "bytes": sum(f["bytes"] for f in entries), "collect_config_hash": collect_hash,
            "recorded": time.strftime("%Y-%m-%d %H:%M:%S"), "files": entries, "links": links}


def summary(record: Mapping[str, Any], path: bool = True) -> str:
    """``/data/x (8 files, hash 1a2b...)``; without ``path``, ``8 files, hash 1a2b...``."""
    what = f"{record.get('n_files', len(record.get('files') or []))} files, hash {record.get('hash')}"
    return f"{record.get('path')} ({what})" if path else what


def differences(before: Mapping[str, Any], now: Mapping[str, Any]) -> str:
    """How ``now``'s files differ from ``before``'s, in a few words (empty when they are the same files)."""
    old = {f["name"]: f for f in before.get("files") or []}
    new = {f["name"]: f for f in now.get("files") or []}
    added = sorted(set(new) - set(old))
    missing = sorted(set(old) - set(new))
    changed = sorted(n for n in set(old) & set(new)
                     if (old[n].get("bytes"), old[n].get("sha256")) != (new[n].get("bytes"), new[n].get("sha256")))
    parts = []
    for what, names in (("added", added), ("missing", missing), ("changed", changed)):
        if names:
            parts.append(f"{len(names)} file(s) {what} ({', '.join(names[:3])}{', ...' if len(names) > 3 else ''})")
    return ", ".join(parts)


def same_place(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """Whether two data paths name the same folder or glob (links resolved)."""
    return os.path.realpath(absolute(a)) == os.path.realpath(absolute(b))


def is_record(value: Any) -> bool:
    return isinstance(value, Mapping) and isinstance(value.get("path"), str) and isinstance(value.get("files"), list)


def every_path_hash(record: Mapping[str, Any]) -> str:
    """``record``'s fingerprint as records written before links were counted once made it: each link an entry of
    its own, with its file's size and SHA-256."""
    by_name = {f["name"]: f for f in record.get("files") or []}
    links = [{**by_name[link["same_as"]], "name": link["name"]} for link in record.get("links") or []
             if link.get("same_as") in by_name]
    return files_hash([*(record.get("files") or []), *links])


def same_files(recorded: Mapping[str, Any], now: Mapping[str, Any]) -> bool:
    """Whether ``now`` holds the files ``recorded`` does, compared the way ``recorded`` was made: a record that
    hashed every path (``HASH_OF_EVERY_PATH``) against ``now`` with its links counted as files."""
    if recorded.get("hash") == now.get("hash"):
        return True
    every_path = recorded.get("hash_of", HASH_OF_EVERY_PATH) == HASH_OF_EVERY_PATH
    return every_path and recorded.get("hash") == every_path_hash(now)


def check_same_data(recorded: Mapping[str, Any], now: Mapping[str, Any], key: str, whose: str, instead: str) -> None:
    """One ``OtherData`` line when ``now`` holds other files than ``recorded`` (the same files in another
    folder are the same data): both named, with what differs. ``key`` names what gave ``now``
    (``data.path``), ``whose`` the run that recorded the other (``the checkpoint``), ``instead`` what to do."""
    if same_files(recorded, now):
        return
    diff = differences(recorded, now) or "other contents"
    raise OtherData(f"{key}={now.get('path')} ({summary(now, path=False)}) is not the data {whose} trained on "
                    f"({summary(recorded)}): {diff}; {instead}",
                    key=key, value=str(now.get("path")))


def recorded_files(recorded: Mapping[str, Any], root: str | os.PathLike | None, key: str, whose: str,
                   instead: str) -> tuple[list[Path], list[str]]:
    """The recorded files under ``root`` (default: the recorded root), each checked (size, and the SHA-256
    of a file whose size or modification time changed): a file missing or changed is one ``OtherData`` line
    naming both folders. Returns the files (absolute paths, in the recorded order) and the names of HDF5
    files under ``root`` that the record does not hold (added since)."""
    root = Path(absolute(root if root is not None else recorded.get("root") or data_root(str(recorded["path"]))))
    names = [str(f["name"]) for f in recorded.get("files") or []]
    present = [root / n for n in names if (root / n).is_file()]
    now = {"path": str(root), "files": _entries(present, root, recorded)}
    now.update(hash=files_hash(now["files"]), n_files=len(now["files"]))
    if len(present) != len(names) or now["hash"] != files_hash(recorded.get("files") or []):
        diff = differences(recorded, now) or "other contents"
        # counted as files (a collected episode may span several), all the folder holds and the recorded ones
        held = len(_hdf5_under(root, root))
        raise OtherData(f"{key}={root} (holding {held} HDF5 file(s), {len(present)} of the {len(names)} recorded "
                        f"ones) no longer holds the data {whose} trained on ({summary(recorded)}): {diff}; "
                        f"{instead}", key=key, value=str(root))
    pattern = recorded["path"] if str(root) == str(recorded.get("root")) else str(root)  # a recorded glob: its files
    every = _hdf5_under(pattern, root) or set(names)
    return [root / n for n in names], sorted(every - set(names))


def _hdf5_under(pattern: str | os.PathLike, root: Path) -> set[str]:
    """The names (relative to ``root``) of the HDF5 files a folder or glob holds, each file once as the loader
    reads it (a link to one is none added); empty when it holds none."""
    try:
        return {_name(f, root) for f in distinct_files(find_files(str(pattern)))[0]}
    except FileNotFoundError:
        return set()


def folder_record(folder: str | os.PathLike) -> dict[str, Any] | None:
    """The record a run folder holds (``<folder>/data.json``), None when it holds none."""
    try:
        record = json.loads((Path(folder) / RECORD_FILE).read_text())
    except (OSError, ValueError):
        return None
    return record if is_record(record) else None


def write_record(folder: str | os.PathLike, record: Mapping[str, Any]) -> None:
    """``<folder>/data.json``, written whole or not at all."""
    atomic_write(Path(folder) / RECORD_FILE, json.dumps(record, indent=1) + "\n")


def with_earlier(record: Mapping[str, Any], earlier: Mapping[str, Any]) -> dict[str, Any]:
    """``record`` keeping ``earlier`` (and what it kept) under ``before``: a run resumed on other data
    records both."""
    kept = [*(earlier.get("before") or []), {k: v for k, v in earlier.items() if k != "before"}]
    return {**record, "before": kept}
