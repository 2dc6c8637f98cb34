"""The collector: CIL files that read back through cicfw.data.cil_hdf5, determinism, resume."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_module

import cicfw.collect as collect_mod
from cicfw.collect import CollectConfigError, collect_dataset, resolve_config
from cicfw.data.cil_hdf5 import T, check_file, find_files, read_rgb, read_targets

SMALL = {"episodes": 2, "seconds": 8, "workers": 0}  # 80 steps x 3 cameras = 240 samples = 2 files each


@pytest.fixture(scope="module")
def small_dataset(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("collected")
    collect_dataset(SMALL, out, progress=False)
    return out


def test_files_read_back_with_cil_values(small_dataset: Path):
    files = find_files(small_dataset)
    assert [f.name for f in files] == [f"ep0000_town_a_ClearNoon_00{i}.h5" for i in range(2)] + \
        [f"ep0001_town_a_ClearSunset_00{i}.h5" for i in range(2)]
    assert [check_file(f).n for f in files] == [200, 40, 200, 40]
    t = np.vstack([read_targets(f) for f in files[:2]])
    rgb = np.concatenate([read_rgb(f) for f in files[:2]])
    assert t.shape == (240, 28) and rgb.shape == (240, 88, 200, 3) and rgb.dtype == np.uint8
    assert set(np.unique(t[:, T.COMMAND])) <= {2, 3, 4, 5}
    assert np.array_equal(t[:, T.CAMERA_ID], np.tile([0, 1, 2], 80))
    assert np.array_equal(t[:, T.CAMERA_YAW], np.tile([0, -30, 30], 80))
    step = t[::3]
    assert np.all((step[:, T.SPEED] >= 0) & (step[:, T.SPEED] < 40)) and step[-1, T.SPEED] > 10
    assert np.all(np.diff(step[:, T.GAME_TIME]) == 100)  # ms, 10 Hz
    assert np.allclose(np.hypot(step[:, T.ORIENT_X], step[:, T.ORIENT_Y]), 1.0, atol=1e-5)
    moved = np.hypot(np.diff(step[:, T.POS_X]), np.diff(step[:, T.POS_Y]))
    assert np.allclose(moved, step[:-1, T.SPEED] / 3.6 * 0.1, atol=0.08)  # positions follow the speed
    assert np.all(np.abs(step[:, T.STEER]) <= 1) and np.all(step[:, T.GAS] >= 0)
    clean = step[:, T.NOISE_FLAG] == 0
    assert np.array_equal(step[clean, T.STEER_NOISE], step[clean, T.STEER])
    # the three cameras of a step see different images, and each step's rows agree but for the camera
    assert not np.array_equal(rgb[0], rgb[1]) and not np.array_equal(rgb[0], rgb[2])
    assert np.array_equal(np.delete(t[0], [T.CAMERA_ID, T.CAMERA_YAW]), np.delete(t[2], [T.CAMERA_ID, T.CAMERA_YAW]))
    meta = json.loads((small_dataset / "dataset_metadata.json").read_text())
    assert meta["complete"] and meta["counts"]["samples"] == 480 and meta["towns"] == ["town_a"]
    assert meta["sim_version"] and meta["weathers"] == ["ClearNoon", "ClearSunset"]
    assert meta["files"]["ep0001_town_a_ClearSunset_001.h5"] == {"episode": "ep0001_town_a_ClearSunset",
                                                                 "samples": 40}


def test_noise_label_is_the_experts_steer_not_the_noisy_one(tmp_path: Path):
    collect_dataset({"episodes": 1, "seconds": 20, "workers": 0, "cameras": ["centre"],
                     "noise": {"episode_fraction": 1.0}}, tmp_path, progress=False)
    t = np.vstack([read_targets(f) for f in find_files(tmp_path)])
    noisy = t[:, T.NOISE_FLAG] == 1
    assert noisy.mean() > 0.2
    assert np.abs(t[noisy, T.STEER_NOISE] - t[noisy, T.STEER]).max() > 0.1


def test_same_seed_same_bytes_and_resume_after_an_interrupted_run(tmp_path: Path, small_dataset: Path,
                                                                   monkeypatch):
    real_write = collect_mod.write_file
    calls = {"n": 0}

    def dying_write(path, rgb, targets):  # episode 0 finishes, episode 1 dies writing its 2nd file
        calls["n"] += 1
        if calls["n"] == 4:
            raise KeyboardInterrupt("killed")
        return real_write(path, rgb, targets)

    out = tmp_path / "resumed"
    monkeypatch.setattr(collect_mod, "write_file", dying_write)
    with pytest.raises(KeyboardInterrupt):
        collect_dataset(SMALL, out, progress=False)
    visible = sorted(p.name for p in out.glob("*.h5"))
    assert visible == ["ep0000_town_a_ClearNoon_000.h5", "ep0000_town_a_ClearNoon_001.h5"]
    assert list(out.glob(".*.part"))  # the dead episode's first file, never under its final name
    meta = json.loads((out / "dataset_metadata.json").read_text())
    assert not meta["complete"] and meta["counts"]["episodes"] == 1
    monkeypatch.setattr(collect_mod, "write_file", real_write)
    collect_dataset(SMALL, out, progress=False)
    assert not [p for p in out.rglob(".*") if p.is_file() and p.parent == out]  # no temporary files left
    assert json.loads((out / "dataset_metadata.json").read_text())["complete"]
    for f in find_files(small_dataset):  # same seed, same bytes, whether interrupted or not
        assert (out / f.name).read_bytes() == f.read_bytes(), f.name
    # a third run has nothing to do and does not touch the files
    before = {p.name: p.stat().st_mtime_ns for p in out.glob("*.h5")}
    collect_dataset(SMALL, out, progress=False)
    assert before == {p.name: p.stat().st_mtime_ns for p in out.glob("*.h5")}


def test_another_seed_gives_other_data(tmp_path: Path, small_dataset: Path):
    collect_dataset({**SMALL, "episodes": 1, "seed": 1}, tmp_path, progress=False)
    a = read_targets(tmp_path / "ep0000_town_a_ClearNoon_000.h5")
    b = read_targets(small_dataset / "ep0000_town_a_ClearNoon_000.h5")
    assert not np.array_equal(a[:, T.POS_X], b[:, T.POS_X])


def test_bad_config_values_give_one_clear_error(tmp_path: Path, small_dataset: Path):
    with pytest.raises(CollectConfigError, match="unknown key 'episode'.*episodes"):
        resolve_config({"episode": 3})
    with pytest.raises(CollectConfigError, match="unknown camera 'top'"):
        resolve_config({"cameras": ["top"]})
    with pytest.raises(ValueError, match="unknown town 'town_q'"):
        resolve_config({"towns": ["town_q"]})
    with pytest.raises(CollectConfigError, match="collect.expert: unknown key 'speed'"):
        resolve_config({"expert": {"speed": 3}})
    with pytest.raises(CollectConfigError, match="another config"):
        collect_dataset({**SMALL, "seconds": 9}, small_dataset, progress=False)


def test_hydra_collect_config_composes_and_resolves():
    with initialize_config_module("cicfw.conf", version_base="1.3"):
        cfg = compose("collect", overrides=["episodes=3", "towns=[town_a,town_b]"])
    resolved = resolve_config(cfg)
    assert resolved["episodes"] == 3 and resolved["towns"] == ["town_a", "town_b"]
    assert resolve_config({}) == resolve_config(None)  # data.collect: {} = the defaults
    assert set(resolve_config({})) == set(collect_mod.DEFAULTS)
