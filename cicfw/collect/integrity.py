"""Whether a dataset's files are sound: each against its recorded size and SHA-256 (or, for files collected
before checksums were kept, its CIL layout), per finished episode as a collection resumes, and for the
whole folder as ``cicfw collect --verify`` checks it, changing nothing (``verify_dataset``)."""
from __future__ import annotations

import json
import logging
import os
from pathlib import Path

from cicfw.collect.config import episode_plan
from cicfw.collect.errors import CollectError
from cicfw.collect.lock import READS_ONLY, FolderLock
from cicfw.collect.metadata import META_NAME
from cicfw.collect.writing import write_json
from cicfw.data.cil_hdf5 import CILFormatError, check_file, is_hdf5_name
from cicfw.data.provenance import file_sha256  # noqa: F401  (a training run's record hashes its files the same way)

log = logging.getLogger(__name__)


def file_problem(out_dir: Path, f: dict) -> tuple[str, str] | None:
    """What is wrong with one recorded file of a marker, as (kind, one-line reason), or None when it is
    sound: ``missing``; ``corrupt`` (another size, another SHA-256, or, without a recorded checksum, not a
    CIL file with the recorded number of samples)."""
    p = out_dir / f["name"]
    try:
        size = p.stat().st_size
    except FileNotFoundError:
        return "missing", "no such file"
    except OSError as err:
        return "missing", f"cannot read it ({err.strerror or err})"
    if "bytes" in f and size != f["bytes"]:
        return "corrupt", f"{size} bytes, {f['bytes']} when it was written (truncated or overwritten)"
    try:
        if "sha256" in f:
            now = file_sha256(p)
            if now != f["sha256"]:
                return "corrupt", (f"its bytes no longer match the checksum recorded when it was written "
                                   f"(sha256 {now[:16]}..., recorded {f['sha256'][:16]}...)")
            return None
        n = check_file(p).n
    except CILFormatError as err:
        return "corrupt", str(err).removeprefix(f"{p}: ")
    except OSError as err:
        return "missing", f"cannot read it ({err.strerror or err})"
    if n != f["samples"]:
        return "corrupt", f"{n} samples, {f['samples']} when it was written"
    return None


def marker_problems(out_dir: Path, m: dict) -> list[tuple[str, str, str]]:
    """(file name, kind, reason) for every file of the marker that is not sound; a marker without files
    is a problem of its own."""
    if not m.get("files"):
        return [(f"{m.get('id', '?')} (no files recorded)", "corrupt", "its marker records no file")]
    out = []
    for f in m["files"]:
        problem = file_problem(out_dir, f)
        if problem is not None:
            out.append((f["name"], *problem))
    return out


def read_markers(out_dir: Path, plan: list[dict], chash: str, say: bool = False) -> dict[str, dict]:
    """The markers of planned episodes whose files are all sound. ``say``: a warning per unsound file of a
    finished episode (its episode is collected again)."""
    markers = {}
    for ep in plan:
        mp = out_dir / ".episodes" / f"{ep['id']}.json"
        try:
            m = json.loads(mp.read_text())
        except (OSError, ValueError):
            continue
        if m.get("config_hash", chash) != chash or m.get("seed") != ep["seed"]:
            continue
        problems = marker_problems(out_dir, m)
        if not problems:
            markers[ep["id"]] = m
        elif say:
            for name, kind, why in problems:
                log.warning("%s: %s: %s; episode %s is collected again", out_dir / name, kind, why, ep["id"])
    return markers


def record_checksums(out_dir: Path, markers: dict[str, dict]) -> int:
    """Record the SHA-256 of files of markers written before checksums were kept (those files have just
    been checked for size and layout); returns how many files got one."""
    n = 0
    for ep_id, m in markers.items():
        legacy = [f for f in m["files"] if "sha256" not in f]
        if not legacy:
            continue
        for f in legacy:
            st = (out_dir / f["name"]).stat()  # before hashing: a change while it is read gives another mtime
            f.update(bytes=st.st_size, mtime_ns=st.st_mtime_ns, sha256=file_sha256(out_dir / f["name"]))
        write_json(out_dir / ".episodes" / f"{ep_id}.json", m)
        n += len(legacy)
    if n:
        log.info("recorded the checksums of %d file(s) of %s collected before cicfw kept checksums (until now "
                 "they could be checked for size and layout only)", n, out_dir)
    return n


def _marker_names(out_dir: Path, plan: list[dict], chash: str) -> set[str]:
    """The file names the markers of planned episodes (``.episodes/<id>.json``, this config's) record."""
    names: set[str] = set()
    for ep in plan:
        try:
            m = json.loads((out_dir / ".episodes" / f"{ep['id']}.json").read_text())
            if m.get("config_hash", chash) == chash and m.get("seed") == ep["seed"]:
                names.update(str(f["name"]) for f in m["files"])
        except (OSError, ValueError, TypeError, KeyError, AttributeError):  # no marker, or not one of ours
            continue
    return names


def foreign_files(out_dir: Path, plan: list[dict], chash: str) -> list[Path]:
    """HDF5 files (suffixes in any case, as the reader finds them) this collection did not write: in a folder
    with its metadata (written before the first episode), any but the planned episodes' files; without it,
    any its episode markers do not record (a collection's files copied without its records are the user's)."""
    if (out_dir / META_NAME).exists():
        ids = tuple(ep["id"] + "_" for ep in plan)
        ours = lambda p: p.name.startswith(ids)  # noqa: E731
    else:
        recorded = _marker_names(out_dir, plan, chash)
        ours = lambda p: p.name in recorded  # noqa: E731
    return [p for p in sorted(out_dir.rglob("*")) if is_hdf5_name(p) and p.is_file()
            and (p.parent != out_dir or p.suffix != ".h5" or not ours(p))]


#: verify's kind for an HDF5 file this collection did not write (``foreign_files``)
FOREIGN = "foreign"


def _planned(meta: dict) -> list[dict] | None:
    """The episodes a collection's metadata plans (from the config it records); None when it records none."""
    try:
        return episode_plan(meta["config"])
    except (KeyError, TypeError, ValueError, AttributeError):
        return None


class VerifyReport:
    """What ``verify_dataset`` found: ``problems`` as (path, kind, reason), kind one of ``missing``,
    ``corrupt``, ``unfinished`` (a file of an episode without a marker: a rerun removes it), ``foreign`` (an
    HDF5 file this collection did not write, as collect calls it: it refuses the folder while it is there)."""

    def __init__(self, out_dir: Path) -> None:
        self.out_dir = out_dir
        self.files = self.bytes = self.unchecked = self.episodes = self.planned = 0
        self.complete = False
        self.problems: list[tuple[Path, str, str]] = []

    def lines(self) -> list[str]:
        """One line per file that is not sound."""
        return [f"{kind}: {path}: {why}" for path, kind, why in self.problems]

    @property
    def ok(self) -> bool:
        return not self.problems and self.complete

    def summary(self) -> str:
        if self.problems:
            foreign = sum(kind == FOREIGN for _, kind, _ in self.problems)
            ours = len(self.problems) - foreign
            said = [f"{foreign} HDF5 file(s) in {self.out_dir} this collection did not write (listed above): move "
                    f"them out of it (collect refuses a folder holding them, and training reads every HDF5 file in it)"
                    ] if foreign else []
            if ours:
                said.append(f"{ours} of {self.files} file(s) of {self.out_dir} are missing, corrupt or unfinished "
                            f"(listed above); {'then ' if foreign else ''}rerun the same collect command (without "
                            f"verify) to collect their episodes again")
            return "; ".join(said)
        if not self.complete:
            return (f"{self.out_dir} is an unfinished dataset ({self.episodes} of {self.planned} episode(s) "
                    f"finished; the files of those are sound); rerun the same collect command to finish it")
        legacy = (f"; {self.unchecked} collected before cicfw kept checksums were checked for size and layout "
                  f"only (a rerun of collect records their checksums)" if self.unchecked else "")
        return (f"verified {self.out_dir}: {self.episodes} episode(s), {self.files} file(s) ({self.bytes / 1e6:.1f} MB), "
                f"all match their checksums{legacy}")


def verify_dataset(out_dir: str | Path, lock_wait: float | None = 0.0) -> VerifyReport:
    """Check every file of a collected dataset against its recorded size and SHA-256 (files without a
    recorded checksum: size and CIL layout), changing nothing. Holds the folder's lock while it reads (a
    collection in progress is waited for as ``lock_wait`` says; a collector starting meanwhile waits, told the
    folder is being verified; a record left by a dead collector lies under a free flock, which the kernel
    frees whenever its holder dies, and is taken over), unless the folder is read-only (then no one can be
    writing into it). A folder without ``dataset_metadata.json`` is a CollectError."""
    out_dir = Path(out_dir).expanduser().resolve()
    meta_path = out_dir / META_NAME
    if not meta_path.is_file():
        what = "does not exist" if not out_dir.exists() else f"has no {META_NAME} (cicfw collect writes one)"
        raise CollectError(f"no dataset to verify in {out_dir}: it {what}; give the out_dir of a collection "
                           f"(out_dir=...)", key="out_dir", value=out_dir)
    lock = None
    if os.access(out_dir, os.W_OK | os.X_OK):
        lock = FolderLock(out_dir, lock_wait, {"what": "cicfw collect verify=true", READS_ONLY: True}).acquire()
    try:
        try:
            meta = json.loads(meta_path.read_text())
        except ValueError:
            raise CollectError(f"{meta_path} is not valid JSON; this folder's dataset cannot be verified: "
                               f"delete it and collect again") from None
        rep = VerifyReport(out_dir)
        rep.planned = int(meta.get("planned_episodes", 0))
        recorded: set[str] = set()
        for mp in sorted((out_dir / ".episodes").glob("*.json")):
            try:
                m = json.loads(mp.read_text())
            except (OSError, ValueError):
                continue  # an unreadable marker: its episode counts as unfinished
            if m.get("config_hash", meta.get("config_hash")) != meta.get("config_hash"):
                continue
            rep.episodes += 1
            problems = {name: (kind, why) for name, kind, why in marker_problems(out_dir, m)}
            for f in m.get("files", []):
                recorded.add(f["name"])
                rep.files += 1
                rep.bytes += int(f.get("bytes", 0))
                rep.unchecked += "sha256" not in f
                if f["name"] in problems:
                    rep.problems.append((out_dir / f["name"], *problems.pop(f["name"])))
            rep.problems += [(out_dir / name, kind, why) for name, (kind, why) in problems.items()]
        plan = _planned(meta)
        foreign = set(foreign_files(out_dir, plan, meta.get("config_hash"))) if plan is not None else set()
        for p in sorted(set(out_dir.glob("*.h5")) | foreign):
            if p in foreign:
                rep.files += 1
                rep.problems.append((p, FOREIGN, "this collection did not write it (a file of yours, a copy or a "
                                                 "link): collect refuses the folder while it is there"))
            elif p.name not in recorded:
                rep.files += 1
                rep.problems.append((p, "unfinished", "no finished episode records it (a collection stopped "
                                                      "before its episode's marker was written)"))
        rep.complete = bool(meta.get("complete")) and rep.episodes >= rep.planned
        return rep
    finally:
        if lock is not None:
            lock.release()
