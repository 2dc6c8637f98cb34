"""The frame table: every usable sample of a CIL dataset as flat arrays, after the paper's filters.

Reads only ``targets`` (small); images stay on disk until the dataset asks for them.
"""
from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cicfw import COMMANDS
from cicfw.data.cil_hdf5 import (COMMAND_CODES, KNOWN_CAMERA_IDS, CILFormatError, T, check_file, find_files,
                                 read_targets)

log = logging.getLogger(__name__)

#: |targets[10]| above this (km/h) cannot be a car's speed: the file is an error (its targets are not in
#: the CIL layout). Negative speeds within it are kept as recorded: CARLA's forward speed is signed (a
#: car rolling backwards, e.g. after a collision), the public CoRL-2017 data has such rows, and CIL's own
#: agent feeds the measured forward speed to the network unchanged, so training sees what driving sees.
MAX_ABS_SPEED_KMH = 300.0


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


def episode_groups(files: list[Path]) -> np.ndarray:
    """Episode id per file: from ``dataset_metadata.json`` (key ``files``: name -> {episode}) when a
    folder has one, else each file is its own episode (CoRL-2017 files are separate recordings)."""
    meta_cache: dict[Path, dict] = {}
    keys: list[str] = []
    for f in files:
        if f.parent not in meta_cache:
            meta = f.parent / "dataset_metadata.json"
            meta_cache[f.parent] = json.loads(meta.read_text()).get("files", {}) if meta.exists() else {}
        entry = meta_cache[f.parent].get(f.name)
        keys.append(f"{f.parent}/episode:{entry['episode']}" if entry and "episode" in entry else str(f))
    _, groups = np.unique(np.array(keys), return_inverse=True)
    return groups.astype(np.int32)


def load_frames(
    path: str,
    max_abs_steer: float = 0.8,
    side_camera_correction: float = 0.15,
    cameras: tuple[int, ...] | None = None,
) -> Frames:
    """Scan ``path`` (folder or glob), check every file, read targets and apply the filters.

    - rows whose steer or speed is NaN/inf are dropped (counted, reported once);
    - negative speeds are kept as recorded (signed forward speed; counted, reported once per dataset);
      a speed beyond +-``MAX_ABS_SPEED_KMH`` is an error naming the file and the row;
    - steer of side cameras is corrected: ``steer - correction * yaw / 30`` (yaw in degrees,
      positive right: a camera looking right sees the road drift left, so the label steers left);
    - samples with |corrected steer| > ``max_abs_steer`` are dropped (the paper keeps [-0.8, 0.8]);
    - an unknown command code is an error naming the file;
    - samples of a camera id outside ``cameras`` are dropped; when the id is none of the known ones
      (``KNOWN_CAMERA_IDS``: 0 centre, 1 left, 2 right) the user cannot have meant to leave it out, so
      a warning names the file, its unknown id(s) and the accepted ones, once per file.
    """
    files = find_files(path)
    for f in files:
        check_file(f)
    groups_of_file = episode_groups(files)
    parts, dropped_nan = [], 0
    neg_rows, neg_files, lowest = 0, 0, (0.0, "", 0)  # negative speeds: counted, kept
    for i, f in enumerate(files):
        t = read_targets(f)
        codes = t[:, T.COMMAND]
        finite = np.isfinite(t[:, T.STEER]) & np.isfinite(t[:, T.SPEED])
        dropped_nan += int((~finite).sum())
        bad = ~np.isin(codes[finite], COMMAND_CODES)
        if bad.any():
            found = sorted(set(np.unique(codes[finite][bad]).tolist()))
            raise CILFormatError(
                f"{f}: unknown high-level command code(s) {found} in targets[24]; accepted codes are "
                f"2 (follow), 3 (left), 4 (right), 5 (straight)"
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
            neg_rows += int(negative.sum())
            neg_files += 1
            lowest = min(lowest, (float(speed[negative].min()), f.name, int(np.argmin(np.where(negative, speed, 0)))))
        rows = np.flatnonzero(finite)
        if cameras is not None:
            _warn_unknown_cameras(f, np.nan_to_num(t[rows, T.CAMERA_ID]).astype(np.int32), cameras)
        yaw = np.nan_to_num(t[rows, T.CAMERA_YAW])
        steer = t[rows, T.STEER] - side_camera_correction * yaw / 30.0
        parts.append((np.full(len(rows), i, np.int32), rows.astype(np.int32), steer.astype(np.float32),
                      t[rows, T.SPEED].astype(np.float32), (codes[rows] - 2).astype(np.int64),
                      np.nan_to_num(t[rows, T.CAMERA_ID]).astype(np.int32),
                      np.full(len(rows), groups_of_file[i], np.int32)))
    frames = Frames(files, *(np.concatenate(col) for col in zip(*parts)))
    if dropped_nan:
        log.warning("dropped %d sample(s) whose steer or speed is NaN or inf", dropped_nan)
    if neg_rows:
        log.info("%d sample(s) in %d of %d file(s) have a negative speed (down to %.3g km/h, %s row %d): "
                 "kept as recorded (the signed forward speed of a car rolling backwards, as the CoRL-2017 "
                 "data has it; the encoder sees speed / model.speed_norm_kmh)", neg_rows, neg_files, len(files),
                 *lowest)
    keep = np.abs(frames.steer) <= max_abs_steer
    if cameras is not None:
        keep &= chosen_cameras(frames.camera, cameras)
    return frames.subset(keep)


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
        raise ValueError(f"data.{key}={list(cameras)} keeps none of the {len(camera)} {what} hold camera id(s) "
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
    if not 0.0 < val_fraction < 1.0:
        raise ValueError(f"data.val_fraction must be in (0, 1), got {val_fraction}")
    groups = np.unique(frames.group)
    if len(groups) < 2:
        raise ValueError(
            f"the data holds {len(groups)} episode(s); a train/validation split by episode needs at least 2 files"
        )
    order = np.random.default_rng(seed).permutation(groups)
    n_val = min(len(groups) - 1, max(1, round(val_fraction * len(groups))))
    is_val = np.isin(frames.group, order[:n_val])
    train, val = frames.subset(~is_val), frames.subset(is_val)
    counts = np.bincount(train.command, minlength=len(COMMANDS))
    missing = [name for name, c in zip(COMMANDS, counts) if c == 0]
    whole = np.bincount(frames.command, minlength=len(COMMANDS))
    absent = [name for name, c in zip(COMMANDS, whole) if c == 0]
    if absent:  # no other split can help: say so rather than suggest another seed
        raise ValueError(
            f"the dataset has no samples of command(s) {absent} (samples per command after the filters "
            f"|steer| <= data.max_abs_steer and data.cameras: {dict(zip(COMMANDS, whole.tolist()))}); each "
            f"command trains its own branch, so collect episodes that contain those commands"
        )
    if missing:
        raise ValueError(
            f"the train split has no sample of command(s) {missing} (train counts per command "
            f"{dict(zip(COMMANDS, counts.tolist()))}); collect more episodes with those commands, "
            f"change data.seed, or lower data.val_fraction"
        )
    return train, val
