"""Whether a finished episode's files are sound: each against its recorded size and SHA-256 (or, for files
collected before checksums were kept, its CIL layout)."""
from __future__ import annotations

import json
import logging
from pathlib import Path

from cicfw.collect.writing import write_json
from cicfw.data.cil_hdf5 import CILFormatError, check_file
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
            f["sha256"] = file_sha256(out_dir / f["name"])
        write_json(out_dir / ".episodes" / f"{ep_id}.json", m)
        n += len(legacy)
    if n:
        log.info("recorded the checksums of %d file(s) of %s collected before cicfw kept checksums (until now "
                 "they could be checked for size and layout only)", n, out_dir)
    return n
