"""The train/validation split of CIL HDF5 data as training draws it: the filters, a seeded split of whole
episodes and the validation cameras. Plain functions of their settings, which ``CILDataModule`` trains on and
diagnose redraws a run's split with, without the training stack."""
from __future__ import annotations

import math
from typing import Any, Sequence

from cicfw.core.config_checks import whole_number
from cicfw.core.errors import CicfwError, ConfigError
from cicfw.data.cil_hdf5 import KNOWN_CAMERA_IDS
from cicfw.data.frames import Frames, camera_names, chosen_cameras, load_frames, split_by_episode


def camera_ids(key: str, cameras: Any) -> tuple[int, ...] | None:
    """``data.cameras`` / ``data.val_cameras`` as a tuple of camera ids (targets[26]), None for every
    camera; anything else is one line naming ``key`` (a lone ``5`` is no list to filter by). Ids beyond
    the known three are allowed: a user's own files may hold them (load_frames names any it drops). An id
    listed twice is refused: the camera is read once all the same (``np.isin``), not weighted twice."""
    if cameras is None:
        return None
    accepted = (f"null (every camera) or a list of distinct camera ids (targets[26]) such as "
                f"{list(KNOWN_CAMERA_IDS)} ({camera_names(KNOWN_CAMERA_IDS)})")
    try:
        listed = isinstance(cameras, Sequence) and not isinstance(cameras, str)  # a ListConfig too
        ids = tuple(whole_number(f"data.{key}", c) for c in cameras) if listed else ()
    except ValueError:
        ids = ()
    if not ids or min(ids) < 0 or len(set(ids)) < len(ids):
        raise ConfigError(f"data.{key}", cameras, accepted)
    return ids


def check_split_settings(val_fraction: float, max_abs_steer: float, side_camera_correction: float, cameras: Any,
                         val_cameras: Any) -> tuple[tuple[int, ...] | None, tuple[int, ...] | None]:
    """The ``data.*`` values that decide the split, checked before any file is read: the camera lists as tuples of
    ids (``camera_ids``); a value out of range is one ``ConfigError`` naming its key."""
    if not 0.0 < max_abs_steer <= 1.0:
        raise ConfigError("data.max_abs_steer", max_abs_steer, "in (0, 1]")
    if not 0.0 < val_fraction < 1.0:
        raise ConfigError("data.val_fraction", val_fraction, "in (0, 1)")
    if not math.isfinite(side_camera_correction):  # NaN would train on NaN labels without a word
        raise ConfigError("data.side_camera_correction", side_camera_correction, "a finite steering offset")
    cams, val_cams = camera_ids("cameras", cameras), camera_ids("val_cameras", val_cameras)
    left_out = sorted(set(val_cams) - set(cams)) if cams is not None and val_cams is not None else []
    if left_out:  # the loader reads data.cameras only: these would validate on nothing
        raise CicfwError(f"data.val_cameras={list(val_cams)} is not within data.cameras="
                         f"{list(cams)}: only data.cameras are read, so camera id(s) {left_out} would "
                         f"validate on nothing; camera ids: {camera_names(KNOWN_CAMERA_IDS)} (or your files' own)")
    return cams, val_cams


def split_frames(path: str | Sequence[str], val_fraction: float, seed: int, max_abs_steer: float,
                 side_camera_correction: float, cameras: tuple[int, ...] | None,
                 val_cameras: tuple[int, ...] | None) -> tuple[Frames, Frames, Frames]:
    """Every frame of ``path`` (a folder, or a list of files) the filters keep, then its training and validation
    frames: whole episodes split by ``seed``, the validation ones kept to ``val_cameras`` (settings checked by
    ``check_split_settings``)."""
    frames = load_frames(path, max_abs_steer, side_camera_correction, cameras)
    train, val = split_by_episode(frames, val_fraction, seed)
    if val_cameras is not None:
        # none left: an error naming the ids the validation episodes hold (else no metric after epoch 1)
        chosen = chosen_cameras(val.camera, val_cameras, "val_cameras", "validation samples: they")
        val = val.subset(chosen)
    return frames, train, val
