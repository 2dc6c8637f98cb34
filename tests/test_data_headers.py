"""What the reader makes of odd files and folders: bad layouts and metadata are one error naming the file;
the public data's quirks (NaN camera fields, upper-case suffixes, links, copies, an unfinished collection)
are accepted and reported; filters that leave nothing say which removed what."""
from __future__ import annotations

import json
import logging
import os
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from cicfw.collect import CollectError, collect_dataset
from cicfw.data.cil_hdf5 import N_TARGETS, CILFormatError, T, find_files, write_file
from cicfw.data.frames import load_frames, split_by_episode
from cicfw.testing import make_targets, write_tiny_dataset


def _warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]


def _h5(path, **entries) -> None:
    """A file with the given entries: arrays, h5py links, or the string "group"."""
    with h5py.File(path, "w") as f:
        for key, value in entries.items():
            if isinstance(value, str) and value == "group":
                f.create_group(key)
            else:
                f[key] = value


RGB = np.zeros((4, 88, 200, 3), np.uint8)
TARGETS = np.zeros((4, 28), np.float32)


@pytest.mark.parametrize("entries, key, what", [
    ({"rgb": RGB, "targets": "group"}, "'targets'", "a group"),
    ({"rgb": h5py.SoftLink("/nowhere"), "targets": TARGETS}, "'rgb'", "soft link"),
    ({"rgb": h5py.ExternalLink("missing.h5", "/rgb"), "targets": TARGETS}, "'rgb'", "external link"),
    ({"rgb": RGB, "targets": h5py.SoftLink("/nowhere")}, "'targets'", "soft link"),
])
def test_a_group_or_a_link_that_leads_nowhere_is_one_error_naming_the_file(tmp_path, entries, key, what):
    path = tmp_path / "odd.h5"
    _h5(path, **entries)
    with pytest.raises(CILFormatError) as err:
        load_frames(str(tmp_path))
    msg = str(err.value)
    assert str(path) in msg and key in msg and what in msg and "float32 (N, 28)" in msg


@pytest.mark.parametrize("text, names", [
    ('{"files": ["data_00000.h5"]}', '"files"'),
    ('{"files": {"data_00000.h5": 3}}', "'data_00000.h5'"),
    ('["data_00000.h5"]', "list"),
    ('{"files": {', "not valid JSON"),
])
def test_a_metadata_file_of_another_shape_is_one_error_naming_it(tmp_path, text, names):
    folder = write_tiny_dataset(tmp_path / "data", n_files=2)
    meta = folder / "dataset_metadata.json"
    meta.write_text(text)
    with pytest.raises(ValueError) as err:
        load_frames(str(folder))
    assert str(meta) in str(err.value) and names in str(err.value)


@pytest.mark.parametrize("column", [T.CAMERA_ID, T.CAMERA_YAW])
def test_a_nan_camera_id_or_yaw_drops_the_row_and_says_so_once(tmp_path, caplog, column):
    rng = np.random.default_rng(0)
    t = make_targets(12, rng)
    t[[1, 4, 7], column] = np.nan
    write_file(tmp_path / "a.h5", np.zeros((12, 88, 200, 3), np.uint8), t)
    with caplog.at_level(logging.WARNING, logger="cicfw.data.frames"):
        frames = load_frames(str(tmp_path), max_abs_steer=1.0, cameras=None)
    assert sorted(frames.row.tolist()) == [r for r in range(12) if r not in (1, 4, 7)]
    said = [m for m in _warnings(caplog) if "camera id" in m and "NaN" in m]
    assert len(said) == 1 and "dropped 3 sample(s)" in said[0]


def test_upper_case_suffixes_are_hdf5_files_too(tmp_path):
    folder = write_tiny_dataset(tmp_path / "data", n_files=3)
    (folder / "data_00001.h5").rename(folder / "data_00001.H5")
    (folder / "data_00002.h5").rename(folder / "data_00002.HDF5")
    assert sorted(f.name for f in find_files(folder)) == ["data_00000.h5", "data_00001.H5", "data_00002.HDF5"]
    assert len(load_frames(str(folder), max_abs_steer=1.0).files) == 3


def test_collect_refuses_a_folder_of_upper_case_hdf5_files_the_reader_would_mix_in(tmp_path):
    folder = write_tiny_dataset(tmp_path / "data", n_files=1)
    (folder / "data_00000.h5").rename(folder / "MINE.H5")
    with pytest.raises(CollectError) as err:
        collect_dataset({"episodes": 1, "seconds": 1, "workers": 0}, folder, progress=False)
    assert "MINE.H5" in str(err.value)


def test_an_unfinished_collection_is_named_in_one_warning(tmp_path, caplog):
    folder = write_tiny_dataset(tmp_path / "data", n_files=2)
    meta = {"complete": False, "planned_episodes": 6, "counts": {"episodes": 2},
            "files": {"data_00000.h5": {"episode": "ep0"}, "data_00001.h5": {"episode": "ep1"}}}
    (folder / "dataset_metadata.json").write_text(json.dumps(meta))
    with caplog.at_level(logging.WARNING, logger="cicfw.data.frames"):
        load_frames(str(folder), max_abs_steer=1.0)
    said = [m for m in _warnings(caplog) if "complete: false" in m]
    assert len(said) == 1 and str(folder) in said[0] and "2 of 6" in said[0]
    caplog.clear()
    (folder / "dataset_metadata.json").write_text(json.dumps({**meta, "complete": True}))
    with caplog.at_level(logging.WARNING, logger="cicfw.data.frames"):
        load_frames(str(folder), max_abs_steer=1.0)
    assert not [m for m in _warnings(caplog) if "complete: false" in m]


@pytest.mark.parametrize("link", [os.symlink, os.link])
def test_a_file_reached_by_two_paths_is_read_once(tmp_path, caplog, link):
    folder = write_tiny_dataset(tmp_path / "data", n_files=3)
    link(folder / "data_00000.h5", folder / "data_00009.h5")
    with caplog.at_level(logging.WARNING, logger="cicfw.data.frames"):
        frames = load_frames(str(folder), max_abs_steer=1.0)
    assert [f.name for f in frames.files] == ["data_00000.h5", "data_00001.h5", "data_00002.h5"]
    said = [m for m in _warnings(caplog) if "same file" in m]
    assert len(said) == 1 and "data_00009.h5" in said[0]


@pytest.mark.parametrize("link", [os.symlink, os.link])
def test_a_link_to_one_part_keeps_its_episode_whole_on_one_side_of_the_split(tmp_path, caplog, link):
    folder = write_tiny_dataset(tmp_path / "data", n_files=8)  # 4 episodes of 2 parts each
    episode_of = {f"data_{i:05d}.h5": f"ep{i // 2}" for i in range(8)}
    (folder / "dataset_metadata.json").write_text(json.dumps(
        {"files": {name: {"episode": ep} for name, ep in episode_of.items()}}))
    link(folder / "data_00000.h5", folder / "aa.h5")  # sorts first, and the metadata does not list it
    with caplog.at_level(logging.WARNING, logger="cicfw.data.frames"):
        frames = load_frames(str(folder), max_abs_steer=1.0)
    assert [f.name for f in frames.files] == sorted(episode_of)  # the recorded name is kept
    by_inode = {(folder / name).stat().st_ino: ep for name, ep in episode_of.items()}  # a link's: its file's
    said = [m for m in _warnings(caplog) if "same file" in m]
    assert len(said) == 1 and "aa.h5" in said[0] and "data_00000.h5" in said[0]
    for seed in range(20):
        train, val = split_by_episode(frames, 0.3, seed)
        sides = {}
        for side, part in (("train", train), ("val", val)):
            for i in np.unique(part.file_idx):
                sides.setdefault(by_inode[frames.files[i].stat().st_ino], set()).add(side)
        assert all(len(s) == 1 for s in sides.values()), (seed, sides)
        assert len(sides) == 4


def test_byte_identical_copies_share_one_episode_and_never_straddle_the_split(tmp_path, caplog):
    folder = write_tiny_dataset(tmp_path / "data", n_files=4)
    for i in range(4):
        shutil.copy(folder / f"data_{i:05d}.h5", folder / f"copy_{i:05d}.h5")
    with caplog.at_level(logging.WARNING, logger="cicfw.data.frames"):
        frames = load_frames(str(folder), max_abs_steer=1.0)
    group = {f.name: int(frames.group[frames.file_idx == i][0]) for i, f in enumerate(frames.files)}
    assert all(group[f"copy_{i:05d}.h5"] == group[f"data_{i:05d}.h5"] for i in range(4))
    assert len(set(group.values())) == 4
    said = [m for m in _warnings(caplog) if "byte-identical" in m]
    assert len(said) == 1 and said[0].startswith("4 file(s)")
    for seed in range(5):
        train, val = split_by_episode(frames, 0.3, seed)
        assert not set(train.group.tolist()) & set(val.group.tolist())


def test_filters_that_leave_nothing_say_which_removed_how_many(tmp_path):
    folder = write_tiny_dataset(tmp_path / "data")  # 6 files x 24 samples
    with pytest.raises(ValueError) as err:
        load_frames(str(folder), max_abs_steer=0.0001, cameras=(0, 1, 2))
    msg = str(err.value)
    assert "of 144 sample(s)" in msg and "144 by data.max_abs_steer=0.0001" in msg


def test_two_filters_that_leave_nothing_are_both_counted(tmp_path):
    t = make_targets(12, np.random.default_rng(0))  # cameras cycle centre, left, right
    t[:, T.STEER] = np.resize(np.array([0.5, -0.15, 0.15], np.float32), 12)  # side labels corrected to 0
    write_file(tmp_path / "a.h5", np.zeros((12, 88, 200, 3), np.uint8), t)
    with pytest.raises(ValueError) as err:
        load_frames(str(tmp_path), max_abs_steer=0.1, cameras=(0,))
    msg = str(err.value)
    assert "4 by data.max_abs_steer=0.1" in msg and "8 by data.cameras=[0]" in msg


def test_a_linked_folder_under_the_data_path_is_read_as_a_glob_reads_it(tmp_path):
    """A folder holding a symlink to another folder of HDF5 files: the folder form finds the linked files, as
    the ``**`` glob form does, and a link back up the tree is not a loop."""
    from cicfw.data.cil_hdf5 import find_files

    real = tmp_path / "real"
    real.mkdir()
    for name in ("a.h5", "b.h5"):
        write_file(real / name, np.zeros((2, 88, 200, 3), np.uint8), np.zeros((2, N_TARGETS), np.float32))
    top = tmp_path / "top"
    top.mkdir()
    (top / "linked").symlink_to(real, target_is_directory=True)
    (real / "up").symlink_to(tmp_path, target_is_directory=True)  # a loop
    by_folder = sorted(f.relative_to(top).as_posix() for f in find_files(top))
    by_glob = sorted(Path(f).relative_to(top).as_posix() for f in find_files(str(top / "*" / "*.h5")))
    assert by_folder == by_glob == ["linked/a.h5", "linked/b.h5"]
