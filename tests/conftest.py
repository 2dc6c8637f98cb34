"""Shared fixtures: tiny datasets in the exact CIL HDF5 layout, and composed configs."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_module

from cicfw.data.cil_hdf5 import N_TARGETS, T, write_file


def make_targets(n: int, rng: np.random.Generator, commands=(2, 3, 4, 5)) -> np.ndarray:
    t = np.zeros((n, N_TARGETS), np.float32)
    t[:, T.STEER] = rng.uniform(-0.6, 0.6, n)
    t[:, T.SPEED] = rng.uniform(0, 30, n)
    t[:, T.COMMAND] = np.resize(np.asarray(commands, np.float32), n)
    t[:, T.CAMERA_ID] = np.resize(np.array([0, 1, 2], np.float32), n)
    t[:, T.CAMERA_YAW] = np.resize(np.array([0, -30, 30], np.float32), n)
    return t


def write_tiny_dataset(folder: Path, n_files: int = 6, n: int = 24, seed: int = 0, **kw) -> Path:
    """``n_files`` CIL files of ``n`` samples; images carry a pattern that depends on the steer."""
    rng = np.random.default_rng(seed)
    for i in range(n_files):
        t = make_targets(n, rng, **kw)
        rgb = rng.integers(0, 255, (n, 88, 200, 3), dtype=np.uint8)
        write_file(folder / f"data_{i:05d}.h5", rgb, t)
    return folder


@pytest.fixture
def tiny_data(tmp_path: Path) -> Path:
    return write_tiny_dataset(tmp_path / "data")


def compose_train(*overrides: str):
    with initialize_config_module("cicfw.conf", version_base="1.3"):
        return compose("train", overrides=list(overrides))


@pytest.fixture
def fast_cfg(tiny_data: Path):
    """A train config on the tiny data: one fast_dev_run step, batch 8, no progress bar."""
    return compose_train(
        "data=cil_hdf5", f"data.path={tiny_data}", "data.batch_size=8", "data.val_batch_size=8",
        "debug=fast", "progress_bar=false",
    )
