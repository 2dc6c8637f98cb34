"""The public CoRL-2017 CIL data has negative speeds, and cicfw reads it.

The files in circulation hold 200 samples each, ``rgb`` uint8 (200, 88, 200, 3) and ``targets`` float32
(200, 28), and some rows have a negative forward speed (CARLA reports a car rolling backwards with a
negative speed; an example the hostile pass met: -5.68 km/h at row 36). Those rows are kept as recorded
and counted once per dataset; only what cannot be a speed is refused (NaN/inf rows dropped, a speed
beyond ``MAX_ABS_SPEED_KMH`` an error naming the file).
"""
from __future__ import annotations

import logging
from pathlib import Path

import h5py
import numpy as np
import pytest

from cicfw.data.cil_hdf5 import T
from cicfw.data.frames import MAX_ABS_SPEED_KMH, load_frames


def write_public_like(path: Path, rng: np.random.Generator, negative_rows: dict[int, float]) -> Path:
    """One file as the CoRL-2017 dataset ships them: 200 samples, ``rgb`` and ``targets`` only (written
    with plain h5py, not cicfw's writer), a speed profile that accelerates from rest, every command,
    camera id 0 with yaw 0, and the given rows' speeds negative."""
    n = 200
    t = np.zeros((n, 28), np.float32)
    t[:, T.STEER] = rng.uniform(-0.3, 0.3, n)
    t[:, T.GAS] = 0.5
    t[:, T.SPEED] = np.minimum(np.arange(n) * 0.4, 35.0)
    for row, v in negative_rows.items():
        t[row, T.SPEED] = v
    t[:, T.COMMAND] = np.repeat(np.array([2, 3, 4, 5], np.float32), n // 4)
    t[:, T.GAME_TIME] = np.arange(n) * 100.0
    with h5py.File(path, "w") as f:
        f.create_dataset("rgb", data=rng.integers(0, 255, (n, 88, 200, 3), dtype=np.uint8))
        f.create_dataset("targets", data=t)
    return path


def test_negative_speeds_of_the_public_data_are_kept_and_counted_once(tmp_path, caplog):
    rng = np.random.default_rng(0)
    folder = tmp_path / "SeqTrain"
    folder.mkdir()
    write_public_like(folder / "data_03663.h5", rng, {36: -5.68, 37: -2.5})
    write_public_like(folder / "data_03664.h5", rng, {120: -0.75})
    write_public_like(folder / "data_03665.h5", rng, {})
    with caplog.at_level(logging.INFO, logger="cicfw.data.frames"):
        frames = load_frames(str(folder), cameras=None)
    assert len(frames) == 600  # nothing dropped: every row is a sample
    first = frames.file_idx == 0
    assert frames.speed[first][36] == pytest.approx(-5.68)  # kept as recorded: neither clipped nor made absolute
    assert frames.speed[first][37] == pytest.approx(-2.5)
    assert np.count_nonzero(frames.speed < 0) == 3
    said = [r.getMessage() for r in caplog.records if "negative speed" in r.getMessage()]
    assert len(said) == 1, said  # once per dataset, not once per file
    assert said[0].startswith("3 sample(s) in 2 of 3 file(s) have a negative speed (down to -5.68 km/h")
    assert "kept as recorded" in said[0]


def test_a_speed_that_cannot_be_a_speed_is_refused_naming_file_row_and_bound(tmp_path):
    rng = np.random.default_rng(1)
    write_public_like(tmp_path / "data_00001.h5", rng, {})
    bad = write_public_like(tmp_path / "data_00002.h5", rng, {17: -(MAX_ABS_SPEED_KMH + 1.0)})
    with pytest.raises(ValueError) as err:
        load_frames(str(tmp_path), cameras=None)
    msg = str(err.value)  # the file, the value, where it is, and the bound
    assert all(s in msg for s in (str(bad), f"{-(MAX_ABS_SPEED_KMH + 1.0):g}", "targets[10]", "17",
                                  f"{MAX_ABS_SPEED_KMH:g}")) and "\n" not in msg, msg


def test_nan_and_inf_speeds_are_dropped_not_kept(tmp_path, caplog):
    rng = np.random.default_rng(2)
    path = write_public_like(tmp_path / "data_00001.h5", rng, {5: -1.0})
    with h5py.File(path, "r+") as f:
        t = f["targets"][()]
        t[3, T.SPEED], t[4, T.SPEED] = np.nan, -np.inf
        f["targets"][...] = t
    write_public_like(tmp_path / "data_00002.h5", rng, {})
    with caplog.at_level(logging.INFO, logger="cicfw.data.frames"):
        frames = load_frames(str(tmp_path), cameras=None)
    assert len(frames) == 398 and np.isfinite(frames.speed).all()
    assert any("dropped 2 sample(s) whose steer or speed is NaN or inf" in r.getMessage() for r in caplog.records)
