"""The CIL HDF5 reader, the paper's filters and split, the balanced sampler, augmentation."""
from __future__ import annotations

import h5py
import numpy as np
import pytest
import torch

from cicfw.core.errors import ConfigError
from cicfw.data.augment import AugmentConfig, augment_batch
from cicfw.data.cil_hdf5 import CILFormatError, T, check_file, find_files, read_rgb, write_file
from cicfw.data.datamodule import CILDataModule
from cicfw.data.frames import load_frames, split_by_episode
from cicfw.data.sampler import CommandBalancedBatchSampler
from conftest import make_targets, write_tiny_dataset


def test_find_files_no_match_says_what_is_accepted(tmp_path):
    with pytest.raises(FileNotFoundError) as err:
        find_files(tmp_path / "nothing_here")
    assert "data.path" in str(err.value) and str(tmp_path / "nothing_here") in str(err.value)


def test_extra_datasets_are_ignored(tmp_path):
    rng = np.random.default_rng(0)
    p = tmp_path / "x.h5"
    with h5py.File(p, "w") as f:
        f["rgb"] = rng.integers(0, 255, (5, 88, 200, 3), dtype=np.uint8)
        f["targets"] = make_targets(5, rng)
        f["depth"] = np.zeros((5, 88, 200), np.uint8)
        f["labels"] = np.zeros((5, 88, 200), np.uint8)
    assert check_file(p).n == 5


@pytest.mark.parametrize(
    "datasets, named",  # named: the datasets and the values the message must name
    [
        ({"targets": np.zeros((4, 28), np.float32)}, ["'rgb'", "'images_center'"]),
        ({"rgb": np.zeros((4, 88, 200, 3), np.uint8)}, ["'targets'"]),
        ({"rgb": np.zeros((4, 88, 200, 3), np.float32), "targets": np.zeros((4, 28), np.float32)}, ["'rgb'", "float32"]),
        ({"rgb": np.zeros((4, 66, 200, 3), np.uint8), "targets": np.zeros((4, 28), np.float32)}, ["'rgb'", "66"]),
        ({"rgb": np.zeros((4, 88, 200, 3), np.uint8), "targets": np.zeros((4, 27), np.float32)}, ["'targets'", "27"]),
        ({"rgb": np.zeros((4, 88, 200, 3), np.uint8), "targets": np.zeros((3, 28), np.float32)}, ["'targets'", "4", "3"]),
    ],
)
def test_bad_file_names_file_and_problem(tmp_path, datasets, named):
    p = tmp_path / "bad.h5"
    with h5py.File(p, "w") as f:
        for k, v in datasets.items():
            f[k] = v
    with pytest.raises(CILFormatError) as err:
        load_frames(str(tmp_path))
    assert all(s in str(err.value) for s in ["bad.h5", *named]), err.value


def _rename_images(path, name="images_center"):
    with h5py.File(path, "a") as f:
        f.move("rgb", name)


@pytest.mark.parametrize("in_memory", [True, False])
def test_images_named_images_center_are_read_like_rgb(tmp_path, in_memory):
    """The CoRL-2017 README names the image dataset 'images_center'; files in circulation use 'rgb'."""
    files = find_files(write_tiny_dataset(tmp_path, n_files=4, n=12))
    for f in files[::2]:  # a folder mixing both names
        _rename_images(f)
    assert check_file(files[0]).n == 12
    with h5py.File(files[0], "r") as f:
        assert "rgb" not in f and np.array_equal(read_rgb(files[0]), f["images_center"][()])
    dm = CILDataModule(str(tmp_path), batch_size=8, val_batch_size=4, in_memory=in_memory, augment=False,
                       val_cameras=None)
    dm.setup("fit")
    for part in (dm.train_set, dm.val_set):
        fr = part.frames
        got = part.__getitems__(list(range(len(fr))))["image"]
        for i in range(len(fr)):
            with h5py.File(fr.files[fr.file_idx[i]], "r") as f:
                stored = f["images_center" if "images_center" in f else "rgb"][fr.row[i]]
            assert torch.equal(got[i], torch.from_numpy(stored).permute(2, 0, 1))


def test_a_file_with_neither_image_name_says_both(tmp_path):
    files = find_files(write_tiny_dataset(tmp_path, n_files=2, n=4))
    _rename_images(files[1], "images")
    with pytest.raises(CILFormatError) as err:
        load_frames(str(tmp_path))
    msg = str(err.value)
    assert all(s in msg for s in (files[1].name, "'rgb'", "'images_center'", "images", "targets")), msg


def test_a_bad_images_center_dataset_is_named_as_such(tmp_path):
    p = tmp_path / "bad.h5"
    with h5py.File(p, "w") as f:
        f["images_center"] = np.zeros((4, 88, 200, 3), np.float32)
        f["targets"] = np.zeros((4, 28), np.float32)
    with pytest.raises(CILFormatError) as err:
        check_file(p)
    assert all(s in str(err.value) for s in ("bad.h5", "'images_center'", "float32")), err.value


def test_not_hdf5_at_all(tmp_path):
    (tmp_path / "junk.h5").write_text("hello")
    with pytest.raises(CILFormatError) as err:
        load_frames(str(tmp_path))
    assert "junk.h5" in str(err.value)


def test_unknown_command_code_is_an_error(tmp_path):
    write_tiny_dataset(tmp_path, n_files=2, commands=(2, 3, 7))
    with pytest.raises(CILFormatError) as err:
        load_frames(str(tmp_path))
    assert err.value.value == [7.0]


def test_a_fractional_camera_id_in_a_file_is_an_error_not_camera_0(tmp_path):
    f = find_files(write_tiny_dataset(tmp_path, n_files=2))[1]
    with h5py.File(f, "a") as h:
        t = h["targets"][...]
        t[3, T.CAMERA_ID] = 0.5
        h["targets"][...] = t
    with pytest.raises(CILFormatError) as err:
        load_frames(str(tmp_path))
    assert err.value.value == 0.5 and f.name in str(err.value)


def test_nan_rows_dropped_and_reported_once(tmp_path, caplog):
    rng = np.random.default_rng(1)
    t = make_targets(20, rng)
    t[3, T.STEER] = np.nan
    t[5, T.SPEED] = np.inf
    write_file(tmp_path / "a.h5", rng.integers(0, 255, (20, 88, 200, 3), dtype=np.uint8), t)
    with caplog.at_level("WARNING"):
        frames = load_frames(str(tmp_path), cameras=None)
    assert len(frames) == 18
    assert [r.message for r in caplog.records].count("dropped 2 sample(s) whose steer or speed is NaN or inf") == 1


def test_steer_filter_and_side_camera_correction(tmp_path):
    rng = np.random.default_rng(2)
    t = make_targets(6, rng)
    t[:, T.STEER] = [0.1, 0.1, 0.1, 0.9, -0.85, 0.0]
    t[:, T.CAMERA_ID] = [0, 1, 2, 0, 0, 0]
    t[:, T.CAMERA_YAW] = [0, -30, 30, 0, 0, 0]
    write_file(tmp_path / "a.h5", rng.integers(0, 255, (6, 88, 200, 3), dtype=np.uint8), t)
    frames = load_frames(str(tmp_path), max_abs_steer=0.8, side_camera_correction=0.2, cameras=None)
    # |steer| > 0.8 dropped; the left camera (yaw -30) gets +0.2, the right camera -0.2
    np.testing.assert_allclose(frames.steer, [0.1, 0.3, -0.1, 0.0], atol=1e-6)
    assert frames.camera.tolist() == [0, 1, 2, 0]


def test_split_is_by_episode_and_seeded(tmp_path):
    write_tiny_dataset(tmp_path, n_files=10)
    frames = load_frames(str(tmp_path))
    train, val = split_by_episode(frames, 0.3, seed=0)
    assert not set(train.file_idx.tolist()) & set(val.file_idx.tolist())  # no file on both sides
    assert len(set(val.file_idx.tolist())) == 3
    train2, _ = split_by_episode(frames, 0.3, seed=0)
    assert np.array_equal(train.row, train2.row) and np.array_equal(train.file_idx, train2.file_idx)
    train3, _ = split_by_episode(frames, 0.3, seed=1)
    assert set(train3.file_idx.tolist()) != set(train.file_idx.tolist())


def test_split_without_a_command_in_train_is_an_error(tmp_path):
    # 'right' (code 4) only in one file: whichever side it lands on, seed 0 puts it in val
    write_tiny_dataset(tmp_path, n_files=4, commands=(2, 3, 5))
    rng = np.random.default_rng(3)
    write_file(tmp_path / "z_right_only.h5", rng.integers(0, 255, (8, 88, 200, 3), dtype=np.uint8),
               make_targets(8, rng, commands=(4,)))
    frames = load_frames(str(tmp_path))
    errors = []
    for seed in range(10):
        try:
            split_by_episode(frames, 0.3, seed)
        except ValueError as err:
            errors.append(err)
    assert errors, "some seed must put the only 'right' file into validation"
    assert errors[0].value == ["right"]


def test_balanced_sampler_shares_and_ranks():
    commands = np.array([0] * 100 + [1] * 10 + [2] * 37 + [3] * 5)
    s = CommandBalancedBatchSampler(commands, batch_size=8, num_batches=5, seed=0)
    batches = list(s)
    assert len(batches) == 5
    for b in batches:
        assert np.bincount(commands[b], minlength=4).tolist() == [2, 2, 2, 2]
    ranks = [set(sum(CommandBalancedBatchSampler(commands, 8, 5, 0, r, 2), [])) for r in (0, 1)]
    assert not ranks[0] & ranks[1]
    with pytest.raises(ValueError) as err:
        CommandBalancedBatchSampler(commands, batch_size=10)
    assert (err.value.key, err.value.value) == ("data.batch_size", 10)


def test_augment_changes_pixels_not_shape():
    rng = np.random.default_rng(0)
    x = rng.integers(0, 255, (16, 88, 200, 3), dtype=np.uint8)
    always = AugmentConfig(p_blur=1, p_noise=1, p_dropout=1, p_coarse_dropout=1, p_add=1, p_multiply=1, p_contrast=1)
    y = augment_batch(x.copy(), always, rng)
    assert y.shape == x.shape and y.dtype == np.uint8
    assert (y != x).mean() > 0.5
    never = AugmentConfig(p_blur=0, p_noise=0, p_dropout=0, p_coarse_dropout=0, p_add=0, p_multiply=0, p_contrast=0)
    assert np.array_equal(augment_batch(x.copy(), never, rng), x)
    with pytest.raises(ValueError) as err:
        AugmentConfig.from_dict({"p_blur": 2})
    assert (err.value.key, err.value.value) == ("data.augment.p_blur", 2)
    with pytest.raises(ValueError) as err:
        AugmentConfig.from_dict({"p_blurr": 0.1})
    assert (err.value.key, err.value.value) == ("data.augment", ["p_blurr"])


@pytest.mark.parametrize("in_memory", [True, False])
def test_datamodule_batches(tmp_path, in_memory):
    write_tiny_dataset(tmp_path, n_files=6, n=24)
    dm = CILDataModule(str(tmp_path), batch_size=8, val_batch_size=5, in_memory=in_memory)
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    assert batch["image"].shape == (8, 3, 88, 200) and batch["image"].dtype == torch.uint8
    assert torch.bincount(batch["command"], minlength=4).tolist() == [2, 2, 2, 2]
    val = next(iter(dm.val_dataloader()))
    assert val["image"].shape[0] == 5
    # validation images are the stored pixels, unaugmented
    fr = dm.val_set.frames
    with h5py.File(fr.files[fr.file_idx[0]], "r") as f:
        stored = f["rgb"][fr.row[0]]
    assert torch.equal(val["image"][0], torch.from_numpy(stored).permute(2, 0, 1))


def test_unbalanced_batch_larger_than_the_train_split_is_refused(tmp_path):
    """drop_last batches of more samples than the split holds would train no step and exit as if trained."""
    write_tiny_dataset(tmp_path, n_files=4, n=32)
    dm = CILDataModule(str(tmp_path), batch_size=500, balanced=False, in_memory=True)
    with pytest.raises(ConfigError) as err:
        dm.setup("fit")
    assert (err.value.key, err.value.value) == ("data.batch_size", 500)
    ok = CILDataModule(str(tmp_path), batch_size=8, balanced=False, in_memory=True)
    ok.setup("fit")
    assert len(ok.train_dataloader()) >= 1


def test_collected_parts_copied_without_their_metadata_stay_one_episode(tmp_path, caplog):
    """A collected episode's files copied without dataset_metadata.json were one episode each: its parts
    trained and validated at once. Grouped by their names, with a warning; CoRL-style names stay apart."""
    from cicfw.data.frames import episode_groups

    rng = np.random.default_rng(0)
    for ep in range(6):
        for part in range(2):
            write_file(tmp_path / f"ep{ep:04d}_town_a_ClearNoon_{part:03d}.h5",
                       rng.integers(0, 255, (8, 88, 200, 3), dtype=np.uint8), make_targets(8, rng))
    with caplog.at_level("WARNING", logger="cicfw.data.frames"):
        frames = load_frames(str(tmp_path))
    assert len(np.unique(frames.group)) == 6 and "grouped into 6 episodes" in caplog.text
    for seed in range(5):
        train, val = split_by_episode(frames, 0.3, seed=seed)
        episode = lambda fr: {frames.files[i].name[:6] for i in np.unique(fr.file_idx)}  # noqa: E731
        assert not episode(train) & episode(val)
    corl = write_tiny_dataset(tmp_path / "corl", n_files=3)
    assert len(set(episode_groups(find_files(corl)).tolist())) == 3
