"""The frame table: every usable sample of a CIL dataset as flat arrays, after the paper's filters.

Reads only ``targets`` (small); images stay on disk until the dataset asks for them.
"""
from __future__ import annotations

import hashlib
import logging
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from cicfw import COMMANDS, MAX_ABS_SPEED_KMH
from cicfw.core.errors import CicfwError
from cicfw.core.json_files import read_json
from cicfw.data.cil_hdf5 import (COMMAND_CODES, KNOWN_CAMERA_IDS, CILFormatError, T, check_file, find_files,
                                 read_targets)

log = logging.getLogger(__name__)

# MAX_ABS_SPEED_KMH (cicfw): |targets[10]| above it cannot be a car's speed: the file is an error (its targets
# are not in the CIL layout). Negative speeds within it are kept as recorded: CARLA's forward speed is signed
# (a car rolling backwards, e.g. after a collision), the public CoRL-2017 data has such rows, and CIL's own
# agent feeds the measured forward speed to the network unchanged, so training sees what driving sees.


@dataclass
class Frames:
    """Parallel arrays, one entry per kept sample."""

    files: list[Path]
    file_idx: np.ndarray  # int32 index into files
    row: np.ndarray  # int32 row inside the file
    steer: np.ndarray  # float32, side-camera corrected
    speed: np.ndarray  # float32 km/h
    command: np.ndarray  # int64 branch index = code - 2
    camera: np.ndarray  # int32 camera id
    group: np.ndarray  # int32 episode id (the unit of the train/val split)

    def __len__(self) -> int:
        return len(self.row)

    def subset(self, mask: np.ndarray) -> "Frames":
        return Frames(self.files, *(a[mask] for a in (self.file_idx, self.row, self.steer, self.speed,
                                                        self.command, self.camera, self.group)))


#: written by ``cicfw collect`` into every folder it collects: ``files`` maps a file name to its episode
META_NAME = "dataset_metadata.json"
META_LAYOUT = ('an object whose "files" maps each file name to an object such as {"episode": "ep0000"} '
               "(cicfw collect writes it; without the file each file is its own episode)")


def folder_metadata(folder: Path) -> dict:
    """A folder's ``dataset_metadata.json`` (``{}`` when it has none), checked for what the loader reads;
    anything else is one error naming the file and the layout it needs."""
    meta = folder / META_NAME
    data = read_json(meta, default={})  # a file that cannot be read or is not JSON: one line naming it
    if not isinstance(data, dict):
        raise CicfwError(f"{meta}: holds a JSON {type(data).__name__}; it must be {META_LAYOUT}")
    files = data.get("files", {})
    if not isinstance(files, dict):
        raise CicfwError(f'{meta}: "files" is a JSON {type(files).__name__}; it must be {META_LAYOUT}')
    for name, entry in files.items():
        if not isinstance(entry, dict):
            raise CicfwError(f'{meta}: "files" entry {name!r} is {entry!r}, not an object; it must be {META_LAYOUT}')
    return data


#: a part of a collected episode as cicfw.collect names it: ``<episode id>_<part>.h5`` (ep0003_town_a_ClearNoon_001.h5)
EPISODE_PART = re.compile(r"^(ep\d{4}_.+)_\d{3}\.h5$")


def _named_episode(f: Path, listed: dict) -> tuple[str | None, bool]:
    """The episode a file belongs to by its folder's metadata (``listed``: its ``files``), else by its name
    (``EPISODE_PART``) in a folder whose metadata lists none (None: neither); and whether the name gave it."""
    entry = listed.get(f.name)
    if entry and "episode" in entry:
        return str(entry["episode"]), False
    part = None if listed else EPISODE_PART.match(f.name)
    return (part.group(1), True) if part else (None, False)


def episode_groups(files: list[Path]) -> np.ndarray:
    """Episode id per file: from ``dataset_metadata.json`` (key ``files``: name -> {episode}) when a
    folder has one, else each file is its own episode (CoRL-2017 files are separate recordings), but for
    the parts of a collected episode copied without their metadata, grouped by name (``EPISODE_PART``):
    split one per file, an episode would train and validate at once."""
    meta_cache: dict[Path, dict] = {}
    keys: list[str] = []
    by_name: dict[Path, list[str]] = {}  # folder -> the episode ids its files' names gave
    for f in files:
        if f.parent not in meta_cache:
            meta_cache[f.parent] = folder_metadata(f.parent).get("files", {})
        episode, from_name = _named_episode(f, meta_cache[f.parent])
        keys.append(str(f) if episode is None else f"{f.parent}/episode:{episode}")
        if from_name:
            by_name.setdefault(f.parent, []).append(episode)
    _, groups = np.unique(np.array(keys), return_inverse=True)
    for folder, ids in by_name.items():
        if len(set(ids)) < len(ids):  # some episode has several parts here
            log.warning("%s has no %s: its %d collected file(s) are grouped into %d episodes by their names "
                        "(<episode>_<part>.h5), so that no episode is split between training and validation; "
                        "copy the collection's %s with them to say so", folder, META_NAME, len(ids),
                        len(set(ids)), META_NAME)
    return groups.astype(np.int32)


def distinct_files(files: list[Path]) -> tuple[list[Path], list[tuple[Path, Path]]]:
    """``files`` with each file once: of the paths that are one file (a symlink, a hard link) the one that
    names its episode is kept (recorded in its folder's metadata, else named as a collected part, else the
    first), so a link never takes a part out of its episode. Also returns the (left out, kept) pairs."""
    paths: dict[tuple[int, int], list[int]] = {}  # (device, inode) -> the indices of its paths
    for i, f in enumerate(files):
        st = f.stat()
        paths.setdefault((st.st_dev, st.st_ino), []).append(i)
    listed: dict[Path, dict] = {}

    def rank(i: int) -> int:  # 0: the metadata names its episode, 1: its name does, 2: neither
        f = files[i]
        if f.parent not in listed:
            listed[f.parent] = folder_metadata(f.parent).get("files", {})
        episode, from_name = _named_episode(f, listed[f.parent])
        return 2 if episode is None else int(from_name)

    keep = {ps[0] if len(ps) == 1 else min(ps, key=rank): ps for ps in paths.values()}  # min: the first of a rank
    kept = [f for i, f in enumerate(files) if i in keep]
    owner = {j: i for i, ps in keep.items() for j in ps}
    same = [(files[j], files[owner[j]]) for j in range(len(files)) if owner[j] != j]
    return kept, same


def merge_copies(groups: np.ndarray, copies: list[tuple[int, int]]) -> np.ndarray:
    """Episode ids where each (copy, original) pair of file indices shares one episode, whole episodes
    merged, so no copy validates what its original trains (numbered in order of each's lowest id)."""
    n = int(groups.max()) + 1 if len(groups) else 0
    edges = np.array([(groups[i], groups[j]) for i, j in copies], np.int64).reshape(-1, 2)
    linked = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    return connected_components(linked, directed=False)[1][groups].astype(np.int32)


def find_copies(files: list[Path], digests: dict[int, bytes]) -> list[tuple[int, int]]:
    """(copy, original) file indices of files with the same size and the same ``targets`` digest."""
    first: dict[tuple[int, bytes], int] = {}
    pairs = []
    for i, digest in sorted(digests.items()):
        key = (files[i].stat().st_size, digest)
        if key in first:
            pairs.append((i, first[key]))
        else:
            first[key] = i
    return pairs


def _sizes_shared(files: list[Path]) -> set[int]:
    """Indices of files whose size another file has: the only ones that can be copies."""
    sizes = [f.stat().st_size for f in files]
    counts = Counter(sizes)
    return {i for i, size in enumerate(sizes) if counts[size] > 1}


def _say_unfinished(files: list[Path]) -> None:
    """One warning per folder whose metadata says its collection is unfinished (killed, or still running):
    its files are whole (collect renames a file only once written), so it trains on what is there."""
    for folder in dict.fromkeys(f.parent for f in files):
        meta = folder_metadata(folder)
        if meta.get("complete", True) is False:
            counts = meta.get("counts")
            done = counts.get("episodes", "?") if isinstance(counts, dict) else "?"
            log.warning("%s: %s says complete: false (%s of %s episode(s) collected; a collect was stopped or is "
                        "still running): training on the files it has; rerun the same collect command to finish it",
                        folder, META_NAME, done, meta.get("planned_episodes", "?"))


def _say_same_and_copies(same: list[tuple[Path, Path]], copies: list[tuple[Path, Path]]) -> None:
    if same:
        log.warning("%d path(s) are the same file as another (a symlink or a hard link; e.g. %s is %s): each file "
                    "is read once", len(same), *same[0])
    if copies:
        log.warning("%d file(s) are byte-identical copies of another (same size, same targets; e.g. %s = %s): each "
                    "copy is put in its original's episode, so no copy validates what its original trains",
                    len(copies), *copies[0])


@dataclass
class _Tally:
    """What the reader dropped or noticed across files, reported once per dataset."""

    nan: int = 0  # steer or speed NaN/inf
    nan_camera: int = 0  # camera id or yaw NaN/inf
    neg_rows: int = 0
    neg_files: int = 0
    lowest: tuple[float, str, int] = (0.0, "", 0)  # the most negative speed: value, file, row
    recorded: list = field(default_factory=list)  # per file, |steer| as recorded (before the side-camera correction)


def _columns(f: Path, i: int, t: np.ndarray, cameras: tuple[int, ...] | None, side_camera_correction: float,
             tally: _Tally) -> tuple:
    """One file's usable rows of ``t`` (its targets) as the Frames columns but the group; ``tally``
    gathers the dropped and negative-speed rows. An unknown command code or an impossible speed is an
    error naming the file."""
    codes = t[:, T.COMMAND]
    finite = np.isfinite(t[:, T.STEER]) & np.isfinite(t[:, T.SPEED])
    camera_known = np.isfinite(t[:, T.CAMERA_ID]) & np.isfinite(t[:, T.CAMERA_YAW])
    tally.nan += int((~finite).sum())
    tally.nan_camera += int((finite & ~camera_known).sum())
    bad = ~np.isin(codes[finite], COMMAND_CODES)
    if bad.any():
        found = sorted(set(np.unique(codes[finite][bad]).tolist()))
        raise CILFormatError(
            f"{f}: unknown high-level command code(s) {found} in targets[24]; accepted codes are "
            f"2 (follow), 3 (left), 4 (right), 5 (straight)", value=found
        )
    speed = t[:, T.SPEED]
    beyond = np.flatnonzero(finite & (np.abs(speed) > MAX_ABS_SPEED_KMH))
    if len(beyond):
        r = int(beyond[0])
        raise CILFormatError(
            f"{f}: speed {float(speed[r]):g} km/h in targets[10] at row {r} ({len(beyond)} row(s) beyond "
            f"±{MAX_ABS_SPEED_KMH:g} km/h); a CIL speed is km/h within ±{MAX_ABS_SPEED_KMH:g} (negative: the "
            f"car rolling backwards, kept), so this file's targets are not in the CIL layout")
    negative = finite & (speed < 0)
    if negative.any():
        tally.neg_rows += int(negative.sum())
        tally.neg_files += 1
        tally.lowest = min(tally.lowest, (float(speed[negative].min()), f.name,
                                          int(np.argmin(np.where(negative, speed, 0)))))
    rows = np.flatnonzero(finite & camera_known)
    ids = t[rows, T.CAMERA_ID]
    fractional = ids != np.round(ids)  # astype would truncate 0.5 to camera 0 and train on it as the centre
    if fractional.any():
        r = int(rows[np.argmax(fractional)])
        raise CILFormatError(f"{f}: camera id {float(t[r, T.CAMERA_ID]):g} in targets[26] at row {r}; a camera id "
                             f"is a whole number (0 centre, 1 left, 2 right)", value=float(t[r, T.CAMERA_ID]))
    camera = ids.astype(np.int32)
    if cameras is not None:
        _warn_unknown_cameras(f, camera, cameras)
    tally.recorded.append(np.abs(t[rows, T.STEER]))
    steer = t[rows, T.STEER] - side_camera_correction * t[rows, T.CAMERA_YAW] / 30.0
    return (np.full(len(rows), i, np.int32), rows.astype(np.int32), steer.astype(np.float32),
            t[rows, T.SPEED].astype(np.float32), (codes[rows] - 2).astype(np.int64), camera)


def _say_dropped(tally: _Tally, n_files: int) -> None:
    if tally.nan:
        log.warning("dropped %d sample(s) whose steer or speed is NaN or inf", tally.nan)
    if tally.nan_camera:
        log.warning("dropped %d sample(s) whose camera id (targets[26]) or yaw (targets[27]) is NaN or inf",
                    tally.nan_camera)
    if tally.neg_rows:
        log.info("%d sample(s) in %d of %d file(s) have a negative speed (down to %.3g km/h, %s row %d): "
                 "kept as recorded (the signed forward speed of a car rolling backwards, as the CoRL-2017 "
                 "data has it; the encoder sees speed / model.speed_norm_kmh)", tally.neg_rows,
                 tally.neg_files, n_files, *tally.lowest)


def _nothing_left(path: str, n_files: int, tally: _Tally, read: int, by_steer: int, by_camera: int,
                  max_abs_steer: float, cameras: tuple[int, ...] | None) -> CicfwError:
    """The error for filters that leave no sample: which filter removed how many."""
    removed = [f"{tally.nan} for a NaN or inf steer or speed",
               f"{tally.nan_camera} for a NaN or inf camera id or yaw",
               f"{by_steer} by data.max_abs_steer={max_abs_steer:g} (|steer| after the side-camera correction "
               f"above it; the paper keeps 0.8)"]
    if cameras is not None:
        removed.append(f"{by_camera} by data.cameras={list(cameras)}")
    return CicfwError(f"the filters leave no sample of the {n_files} file(s) of data.path={path!r}: of "
                      f"{read + tally.nan + tally.nan_camera} sample(s), {', '.join(removed)}; loosen the "
                      f"filter that removed them")


def load_frames(
    path: str,
    max_abs_steer: float = 0.8,
    side_camera_correction: float = 0.15,
    cameras: tuple[int, ...] | None = None,
) -> Frames:
    """Scan ``path`` (folder or glob), check every file, read targets and apply the filters.

    - a path that is the same file as another (symlink, hard link) is read once; byte-identical copies
      (same size, same targets) share their original's episode (both reported once);
    - rows whose steer or speed, or camera id or yaw, is NaN/inf are dropped (counted, reported once);
    - negative speeds are kept as recorded (signed forward speed; counted, reported once per dataset);
      a speed beyond +-``MAX_ABS_SPEED_KMH`` is an error naming the file and the row;
    - steer of side cameras is corrected: ``steer - correction * yaw / 30`` (yaw in degrees,
      positive right: a camera looking right sees the road drift left, so the label steers left);
    - samples with |corrected steer| > ``max_abs_steer`` are dropped (the paper keeps [-0.8, 0.8]);
    - an unknown command code is an error naming the file;
    - samples of a camera id outside ``cameras`` are dropped; when the id is none of the known ones
      (``KNOWN_CAMERA_IDS``: 0 centre, 1 left, 2 right) the user cannot have meant to leave it out, so
      a warning names the file, its unknown id(s) and the accepted ones, once per file;
    - filters that leave nothing are an error saying which removed how many;
    - a collected folder whose metadata says ``complete: false`` is named in a warning (trained on).
    """
    files, same = distinct_files(find_files(path))
    for f in files:
        check_file(f)
    groups_of_file = episode_groups(files)
    _say_unfinished(files)
    shared = _sizes_shared(files)
    tally = _Tally()
    parts, digests = [], {}
    for i, f in enumerate(files):
        t = read_targets(f)
        parts.append(_columns(f, i, t, cameras, side_camera_correction, tally))
        if i in shared:
            digests[i] = hashlib.blake2b(t.tobytes(), digest_size=16).digest()
    copies = find_copies(files, digests)
    groups_of_file = merge_copies(groups_of_file, copies)
    _say_same_and_copies(same, [(files[i], files[j]) for i, j in copies])
    _say_dropped(tally, len(files))
    columns = [np.concatenate(col) for col in zip(*parts)]
    frames = Frames(files, *columns, groups_of_file[columns[0]])
    by_steer = np.abs(frames.steer) > max_abs_steer
    keep = ~by_steer
    if cameras is not None:
        keep &= chosen_cameras(frames.camera, cameras)
    if not keep.any():
        raise _nothing_left(path, len(files), tally, len(frames), int(by_steer.sum()),
                            int((~by_steer & ~keep).sum()), max_abs_steer, cameras)
    _say_steer_filter(by_steer, max_abs_steer, np.concatenate(tally.recorded), side_camera_correction)
    return frames.subset(keep)


#: a filter dropping more than this share of the samples says so (the paper's |steer| <= 0.8 drops a few %)
DROP_WARN_SHARE = 0.10


def _say_steer_filter(dropped: np.ndarray, max_abs_steer: float, recorded: np.ndarray, correction: float) -> None:
    """One warning when ``data.max_abs_steer`` drops more than ``DROP_WARN_SHARE`` of the samples: how many,
    why, and the likely cause: steering stored in degrees or radians rather than CIL's [-1, 1], a
    side-camera correction that pushes labels the recorded steer keeps (``recorded``: |steer| as recorded)
    beyond the filter, or a steering scaled otherwise."""
    n, k = len(dropped), int(dropped.sum())
    if not n or k <= DROP_WARN_SHARE * n:
        return
    top, by_recorded = float(recorded.max()), int((recorded > max_abs_steer).sum())
    if top > 1.0:
        cause = (f"the recorded |steer| reaches {top:.3g}, beyond CIL's [-1, 1]: targets[0] likely holds degrees "
                 f"or radians; convert it to [-1, 1] (steering angle / the car's largest angle)")
    elif by_recorded <= DROP_WARN_SHARE * n:  # the recorded labels pass: the correction moved the side cameras'
        fix = ("set it nearer CIL's 0.15" if abs(correction) > 0.15 else  # else the filter is the tighter one
               "raise data.max_abs_steer above that offset (the paper keeps 0.8)")
        cause = (f"as recorded, only {by_recorded} are: data.side_camera_correction={correction:g} (the label "
                 f"offset per 30 deg of camera yaw) moves the side cameras' labels past it; {fix}")
    else:
        cause = "if your steering is in [-1, 1] but scaled otherwise, set data.max_abs_steer to suit it (at most 1)"
    log.warning("data.max_abs_steer=%g drops %d of %d samples (%.0f%%): their |steer| (after the side-camera "
                "correction) is above it; %s", max_abs_steer, k, n, 100.0 * k / n, cause)


def camera_names(ids: dict[int, str]) -> str:
    """``0 centre, 1 left, 2 right``."""
    return ", ".join(f"{i} {name}" for i, name in ids.items())


def chosen_cameras(camera: np.ndarray, cameras: tuple[int, ...], key: str = "cameras",
                   what: str = "samples: the files") -> np.ndarray:
    """The samples of ``data.<key>``; choosing none of the ids the samples hold is an error naming them
    (it used to surface as "the data holds 0 episode(s)", for a folder of many)."""
    chosen = np.isin(camera, list(cameras))
    if len(camera) and not chosen.any():
        held = sorted(set(np.unique(camera).tolist()))
        raise CicfwError(f"data.{key}={list(cameras)} keeps none of the {len(camera)} {what} hold camera id(s) "
                         f"{held} ({camera_names(KNOWN_CAMERA_IDS)}); choose among those, or data.{key}=null for "
                         f"every camera")
    return chosen


def _warn_unknown_cameras(path: Path, camera: np.ndarray, cameras: tuple[int, ...]) -> None:
    """One warning for a file whose samples carry camera ids that are neither chosen nor known."""
    unknown = ~np.isin(camera, list(cameras)) & ~np.isin(camera, list(KNOWN_CAMERA_IDS))
    if not unknown.any():
        return
    ids = sorted(set(np.unique(camera[unknown]).tolist()))
    known = camera_names(KNOWN_CAMERA_IDS)
    log.warning("%s: camera id(s) %s in targets[26] (%d sample(s)) are not among data.cameras %s (known ids: %s); "
                "those samples are dropped: add the id(s) to data.cameras, or set data.cameras=null for every "
                "camera, to train on them", path, ids, int(unknown.sum()), sorted(int(c) for c in cameras), known)


def split_by_episode(frames: Frames, val_fraction: float, seed: int) -> tuple[Frames, Frames]:
    """Seeded split of whole episodes (never frames): ~``val_fraction`` of the episodes validate."""
    groups = np.unique(frames.group)
    if len(groups) < 2:
        held = len(np.unique(frames.file_idx))
        where = (f"{held} of its {len(frames.files)} file(s) keep any sample after the filters "
                 f"(data.max_abs_steer, data.cameras)" if held < len(frames.files) else
                 f"in {len(frames.files)} file(s) (a collected folder's {META_NAME} groups files by episode)")
        raise CicfwError(f"the data holds {len(groups)} episode(s): {where}; a train/validation split by episode needs "
                         f"at least 2 episodes")
    order = np.random.default_rng(seed).permutation(groups)
    n_val = min(len(groups) - 1, max(1, round(val_fraction * len(groups))))
    is_val = np.isin(frames.group, order[:n_val])
    train, val = frames.subset(~is_val), frames.subset(is_val)
    counts = np.bincount(train.command, minlength=len(COMMANDS))
    missing = [name for name, c in zip(COMMANDS, counts) if c == 0]
    whole = np.bincount(frames.command, minlength=len(COMMANDS))
    absent = [name for name, c in zip(COMMANDS, whole) if c == 0]
    if absent:  # no other split can help: say so rather than suggest another seed
        raise CicfwError(
            f"the dataset has no samples of command(s) {absent} (samples per command after the filters "
            f"|steer| <= data.max_abs_steer and data.cameras: {dict(zip(COMMANDS, whole.tolist()))}); each "
            f"command trains its own branch, so collect episodes that contain those commands"
        )
    if missing:
        raise CicfwError(
            f"the train split has no sample of command(s) {missing} (train counts per command "
            f"{dict(zip(COMMANDS, counts.tolist()))}); collect more episodes with those commands, "
            f"change data.seed, or lower data.val_fraction", value=missing
        )
    return train, val
