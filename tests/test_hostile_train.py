"""``cicfw train`` as a hostile user runs it (issue 17): every mistake refused in one line before the
first batch."""
from __future__ import annotations

from pathlib import Path

import pytest

import cicfw.train as train_mod
from cicfw.data.datamodule import CILDataModule
from cicfw.train import train
from conftest import compose_train, write_tiny_dataset

BASE = ("data=cil_hdf5", "data.batch_size=8", "data.val_batch_size=8", "progress_bar=false")
TOWN = str(Path(__file__).parent / "data" / "bench_town.yaml")


@pytest.fixture
def no_data(monkeypatch):
    """Fail loudly if training reaches the data (collecting or reading any file)."""

    def touched(*_a, **_k):
        raise AssertionError("the data was touched before the config error was reported")

    monkeypatch.setattr(train_mod, "ensure_data", touched)
    monkeypatch.setattr(CILDataModule, "setup", touched)


def _cfg(tmp_path: Path, *overrides: str):
    return compose_train(*BASE, f"data.path={tmp_path}/data", *overrides)


def _one_line(err: pytest.ExceptionInfo) -> str:
    text = str(err.value)
    assert "\n" not in text, text
    return text


# ---- item 4: unknown top-level keys --------------------------------------------------------------


@pytest.mark.parametrize("override, message", [
    ("+foo=1", "unknown top-level key 'foo'; accepted top-level keys: ckpt_path, data, encoder, evaluate_after,"),
    ("+evaluate_aftr=true", "unknown top-level key 'evaluate_aftr'; did you mean 'evaluate_after'? accepted "
                            "top-level keys: ckpt_path, data,"),
])
def test_an_unknown_top_level_key_is_refused_before_any_data(tmp_path, no_data, override, message):
    with pytest.raises(ValueError) as err:
        train(_cfg(tmp_path, override), tmp_path / "run")
    assert _one_line(err).startswith(message), str(err.value)
    assert "trainer" in str(err.value) and "seed" in str(err.value)


# ---- item 8: the evaluation's config, checked before the first batch -----------------------------


@pytest.mark.parametrize("overrides, message", [
    (["suite.towns=[town_z]"], "evaluate_overrides: unknown town 'town_z'; known towns: town_a, town_b"),
    (["suite.foo=1"], "evaluate_overrides: suite.foo=1: 'suite' has no key 'foo'"),
    (["suite.limit=0"], "evaluate_overrides: suite.limit must be >= 1 (or null for every pair), got 0"),
    (["suite.towns=[town_a"], "evaluate_overrides: cannot parse 'suite.towns=[town_a': "),
    (["suite=nosuch"], "evaluate_overrides: suite=nosuch: no option 'nosuch' in config group 'suite'; "
                       "options: junctions, single_turn"),
    (["+foo=1"], "evaluate_overrides: unknown top-level key 'foo'; accepted top-level keys: checkpoint,"),
    (["runner.workers=0"], "evaluate_overrides: runner.workers must be an integer >= 1 or 'auto', got 0"),
    (["+runner.foo=1"], "evaluate_overrides: runner.foo is not an argument of the runner; accepted keys: batch_size, "
                         "off_road_level, off_road_s, target_speed_kmh, threads, workers"),
    (["video=[nosuch]"], "evaluate_overrides: video: unknown episode 'nosuch'; give episode indices, keys such as"),
    (["+policy.nosuch=1"], "evaluate_overrides: policy.nosuch is not an argument of policy 'checkpoint'; "
                           "accepted keys: camera, checkpoint, device, fuse, label, name, threads"),
])
def test_bad_evaluate_overrides_are_refused_before_the_first_batch(tmp_path, no_data, overrides, message):
    cfg = _cfg(tmp_path, "evaluate_after=true", f"evaluate_overrides=[{','.join(repr(o) for o in overrides)}]")
    with pytest.raises(ValueError) as err:
        train(cfg, tmp_path / "run")
    assert _one_line(err).startswith(message), str(err.value)


def test_good_evaluate_overrides_pass_the_check():
    from cicfw.evaluate import check_evaluation_overrides

    check_evaluation_overrides([f"suite.towns=[{TOWN}]", "suite.limit=1", "runner.workers=2", "video=[0]"])
    check_evaluation_overrides(["suite=single_turn", "policy.device=cpu"])


# ---- tracebacks where one line belongs -----------------------------------------------------------


@pytest.mark.parametrize("override, message", [
    ("model.lr=abc", "model.lr must be a number, got 'abc'"),
    ("model.betas=abc", "model.betas must be a list of 2 numbers, got 'abc'"),
    ("mixer.hidden=wide", "mixer.hidden must be a number, got 'wide'"),
])
def test_a_value_of_the_wrong_type_is_one_line_before_any_data(tmp_path, no_data, override, message):
    with pytest.raises(ValueError) as err:
        train(_cfg(tmp_path, override), tmp_path / "run")
    assert _one_line(err) == message


def test_a_folder_of_your_own_cil_files_without_data_cil_hdf5_names_it(tmp_path):
    data = write_tiny_dataset(tmp_path / "mine")
    cfg = compose_train("data.batch_size=8", "data.val_batch_size=8", f"data.path={data}", "progress_bar=false")
    with pytest.raises(ValueError) as err:
        train(cfg, tmp_path / "run")
    text = _one_line(err)
    assert text.startswith(f"data.path={data} holds 6 CIL HDF5 file(s) that cicfw did not collect"), text
    assert f"add data=cil_hdf5 to train on them: python -m cicfw.train data=cil_hdf5 data.path={data}" in text
    assert not (data / "dataset_metadata.json").exists()  # nothing collected into the user's folder
