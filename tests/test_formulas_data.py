"""The paper's data rules, with the values of ``conf/data/cil_hdf5.yaml`` (what a user gets):
the side cameras' steering correction and its sign, the |steer| <= 0.8 filter applied after the
correction, minibatches of 120 with 30 per command, and the 70/30 split by episode, never by frame.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from cicfw.data.cil_hdf5 import T, write_file
from cicfw.data.datamodule import CILDataModule
from cicfw.data.frames import load_frames, split_by_episode
from cicfw.data.sampler import CommandBalancedBatchSampler
from conftest import make_targets, write_tiny_dataset

torch.set_num_threads(1)

CONF = OmegaConf.to_container(OmegaConf.load(Path(__file__).resolve().parents[1] / "conf/data/cil_hdf5.yaml"))
CENTRE, LEFT, RIGHT = (0, 0.0), (1, -30.0), (2, 30.0)  # camera id, yaw in degrees (positive right)

# (camera, raw steer, the label the paper's rules give it, or None: dropped)
ROWS = [
    (CENTRE, 0.0, 0.0),
    (LEFT, 0.0, 0.15),     # the left camera sees the road drift right: its label turns right (+)
    (RIGHT, 0.0, -0.15),   # the right camera's label turns left (-)
    (CENTRE, 0.75, 0.75),
    (LEFT, 0.7, None),     # 0.7 passes |steer| <= 0.8 raw, but corrected it is 0.85: dropped
    (RIGHT, 0.9, 0.75),    # 0.9 fails the filter raw, but corrected it is 0.75: kept
    (LEFT, -0.9, -0.75),
    (RIGHT, -0.7, None),   # corrected -0.85: dropped
    (CENTRE, 0.8, 0.8),    # the bound itself is kept
    (CENTRE, -0.81, None),
]


def conf(path: Path, **overrides) -> CILDataModule:
    kw = {**CONF, "path": str(path), "seed": 0, "augment": False, **overrides}
    return CILDataModule(**kw)


def write_rows(path: Path, seed: int = 0) -> None:
    t = make_targets(len(ROWS), np.random.default_rng(seed))  # commands cycle 2, 3, 4, 5; speeds by seed
    for i, ((cam, yaw), steer, _) in enumerate(ROWS):
        t[i, T.CAMERA_ID], t[i, T.CAMERA_YAW], t[i, T.STEER] = cam, yaw, steer
    write_file(path, np.zeros((len(ROWS), 88, 200, 3), np.uint8), t)


def test_the_config_holds_the_papers_values():
    assert CONF["batch_size"] == 120 and CONF["balanced"] is True
    assert CONF["max_abs_steer"] == 0.8 and CONF["val_fraction"] == 0.3
    assert CONF["side_camera_correction"] == 0.15


def test_side_camera_sign_and_the_filter_after_the_correction(tmp_path):
    for i in range(2):  # two episodes (not copies of one), so the datamodule can split them
        write_rows(tmp_path / f"ep{i}.h5", seed=i)
    dm = conf(tmp_path, val_cameras=None)
    dm.setup("fit")
    labels = {}
    for part in (dm.train_set.frames, dm.val_set.frames):
        for row, steer in zip(part.row.tolist(), part.steer.tolist()):
            labels.setdefault(row, set()).add(round(steer, 6))
    expected = {i: {e} for i, (_, _, e) in enumerate(ROWS) if e is not None}
    assert labels == expected


def test_load_frames_defaults_are_the_same_rules(tmp_path):
    write_rows(tmp_path / "ep0.h5")
    frames = load_frames(str(tmp_path))
    kept = [(i, e) for i, (_, _, e) in enumerate(ROWS) if e is not None]
    assert frames.row.tolist() == [i for i, _ in kept]
    np.testing.assert_allclose(frames.steer, [e for _, e in kept], atol=1e-6)


# ---------------------------------------------------------------- 30 per command in 120
def test_sampler_gives_30_of_each_command_in_every_batch_of_120():
    commands = np.array([0] * 500 + [1] * 40 + [2] * 35 + [3] * 7)  # very unbalanced, 'straight' rare
    rng = np.random.default_rng(0)
    commands = commands[rng.permutation(len(commands))]
    sampler = CommandBalancedBatchSampler(commands, batch_size=CONF["batch_size"], seed=0)
    batches = list(sampler)
    assert len(batches) == len(commands) // 120
    for batch in batches:
        assert len(batch) == 120
        assert np.bincount(commands[batch], minlength=4).tolist() == [30, 30, 30, 30]
    # the common command is not repeated within a batch (sampled without replacement)
    assert all(len(set(b) & set(np.flatnonzero(commands == 0))) == 30 for b in batches)


def test_datamodule_batches_hold_30_per_command(tmp_path):
    write_tiny_dataset(tmp_path, n_files=3, n=24)
    dm = conf(tmp_path)
    dm.setup("fit")
    assert len(dm.train_set) < 120  # fewer samples than one batch: the rarer ones repeat
    batches = list(dm.train_dataloader())
    assert len(batches) >= 1
    for batch in batches:
        assert batch["command"].shape == (120,)
        assert torch.bincount(batch["command"], minlength=4).tolist() == [30, 30, 30, 30]


# ---------------------------------------------------------------- the split by episode
def write_episodes(folder: Path, n_episodes: int, files_per_episode: int) -> dict[str, int]:
    rng = np.random.default_rng(1)
    episode_of = {}
    for e in range(n_episodes):
        for part in range(files_per_episode):
            name = f"ep{e:03d}_{part}.h5"
            write_file(folder / name, np.zeros((8, 88, 200, 3), np.uint8), make_targets(8, rng))
            episode_of[name] = e
    meta = {"files": {name: {"episode": e, "samples": 8} for name, e in episode_of.items()}}
    (folder / "dataset_metadata.json").write_text(json.dumps(meta))
    return episode_of


@pytest.mark.parametrize("seed", range(4))
def test_split_keeps_every_episode_whole_on_one_side(tmp_path, seed):
    episode_of = write_episodes(tmp_path, n_episodes=10, files_per_episode=3)
    frames = load_frames(str(tmp_path), cameras=None)
    train, val = split_by_episode(frames, CONF["val_fraction"], seed)
    side = {}
    for name_part, part in (("train", train), ("val", val)):
        for fi in part.file_idx.tolist():
            e = episode_of[frames.files[fi].name]
            side.setdefault(e, set()).add(name_part)
    assert all(len(s) == 1 for s in side.values()), side  # no episode on both sides
    val_eps = {e for e, s in side.items() if s == {"val"}}
    assert len(val_eps) == 3  # 30% of 10 episodes
    assert len(val) == 3 * 3 * 8 and len(train) == 7 * 3 * 8  # whole episodes, every frame of them


def test_split_without_metadata_keeps_every_file_whole(tmp_path):
    write_tiny_dataset(tmp_path, n_files=10, n=12)
    frames = load_frames(str(tmp_path), cameras=None)
    for seed in range(4):
        train, val = split_by_episode(frames, CONF["val_fraction"], seed)
        assert not set(train.file_idx.tolist()) & set(val.file_idx.tolist())
        assert len(set(val.file_idx.tolist())) == 3 and len(val) == 3 * 12
