"""Issue 17, the data layer's hostile cases: nothing the reader drops is dropped without a word."""
from __future__ import annotations

import logging

import h5py
import numpy as np

from cicfw.data.cil_hdf5 import T
from cicfw.data.frames import load_frames
from cicfw.testing import write_tiny_dataset


def _set_camera(path, ids) -> None:
    with h5py.File(path, "r+") as f:
        t = f["targets"][()]
        t[:, T.CAMERA_ID] = np.resize(np.asarray(ids, np.float32), len(t))
        t[:, T.CAMERA_YAW] = 0.0
        f["targets"][...] = t


def _camera_warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records
            if r.levelno == logging.WARNING and "camera id" in r.getMessage()]


def test_a_file_with_an_unknown_camera_id_is_named_once_not_dropped_silently(tmp_path, caplog):
    """Item 5: 6 files x 24 samples; one file's camera id is 7 (none of 0 centre, 1 left, 2 right). Its
    24 samples used to vanish from training without a word (96 -> 72 training samples)."""
    folder = write_tiny_dataset(tmp_path / "data")
    odd = folder / "data_00003.h5"
    _set_camera(odd, [7])
    with caplog.at_level(logging.INFO, logger="cicfw.data.frames"):
        frames = load_frames(str(folder), max_abs_steer=1.0, cameras=(0, 1, 2))
    assert not np.any(frames.camera == 7)  # still not trained on: data.cameras decides
    said = _camera_warnings(caplog)
    assert len(said) == 1, said  # once per file
    msg = said[0]
    assert str(odd) in msg and "[7]" in msg and "24 sample(s)" in msg
    assert "data.cameras [0, 1, 2]" in msg  # the accepted ids
    assert "\n" not in msg


def test_unknown_ids_are_listed_together_once_per_file_and_chosen_ids_are_kept(tmp_path, caplog):
    folder = write_tiny_dataset(tmp_path / "data")
    _set_camera(folder / "data_00001.h5", [3, 4])
    _set_camera(folder / "data_00002.h5", [4])
    with caplog.at_level(logging.INFO, logger="cicfw.data.frames"):
        load_frames(str(folder), max_abs_steer=1.0, cameras=(0, 1, 2))
    said = _camera_warnings(caplog)
    assert len(said) == 2, said
    assert "data_00001.h5" in said[0] and "[3, 4]" in said[0]
    assert "data_00002.h5" in said[1] and "[4]" in said[1]
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="cicfw.data.frames"):  # the user chose them: kept, no warning
        frames = load_frames(str(folder), max_abs_steer=1.0, cameras=(0, 3, 4))
    assert np.count_nonzero(np.isin(frames.camera, [3, 4])) == 48
    assert _camera_warnings(caplog) == []


def test_known_cameras_left_out_on_purpose_raise_no_warning(tmp_path, caplog):
    folder = write_tiny_dataset(tmp_path / "data")
    with caplog.at_level(logging.INFO, logger="cicfw.data.frames"):
        frames = load_frames(str(folder), max_abs_steer=1.0, cameras=(0,))
    assert set(frames.camera.tolist()) == {0}
    assert _camera_warnings(caplog) == []
