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
from cicfw.data.cil_hdf5 import COMMAND_CODES, CILFormatError, T, check_file, find_files, read_targets

log = logging.getLogger(__name__)

#: targets[10] below minus this (km/h) is an error; smaller negative values are sensor noise at a standstill.
NEGATIVE_SPEED_TOLERANCE_KMH = 0.5


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
    - steer of side cameras is corrected: ``steer - correction * yaw / 30`` (yaw in degrees,
      positive right: a camera looking right sees the road drift left, so the label steers left);
    - samples with |corrected steer| > ``max_abs_steer`` are dropped (the paper keeps [-0.8, 0.8]);
    - an unknown command code, or a negative speed, is an error naming the file.
    """
    files = find_files(path)
    for f in files:
        check_file(f)
    groups_of_file = episode_groups(files)
    parts, dropped_nan = [], 0
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
        negative = np.flatnonzero(finite & (speed < -NEGATIVE_SPEED_TOLERANCE_KMH))
        if len(negative):
            r = int(negative[0])
            raise CILFormatError(
                f"{f}: negative speed in targets[10] ({len(negative)} row(s), e.g. {float(speed[r]):g} km/h at "
                f"row {r}); speeds must be >= 0 km/h (the forward speed; down to "
                f"-{NEGATIVE_SPEED_TOLERANCE_KMH:g} is accepted as standstill noise)"
            )
        rows = np.flatnonzero(finite)
        yaw = np.nan_to_num(t[rows, T.CAMERA_YAW])
        steer = t[rows, T.STEER] - side_camera_correction * yaw / 30.0
        parts.append((np.full(len(rows), i, np.int32), rows.astype(np.int32), steer.astype(np.float32),
                      t[rows, T.SPEED].astype(np.float32), (codes[rows] - 2).astype(np.int64),
                      np.nan_to_num(t[rows, T.CAMERA_ID]).astype(np.int32),
                      np.full(len(rows), groups_of_file[i], np.int32)))
    frames = Frames(files, *(np.concatenate(col) for col in zip(*parts)))
    if dropped_nan:
        log.warning("dropped %d sample(s) whose steer or speed is NaN or inf", dropped_nan)
    keep = np.abs(frames.steer) <= max_abs_steer
    if cameras is not None:
        keep &= np.isin(frames.camera, list(cameras))
    return frames.subset(keep)


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
