"""Inputs a new user gets wrong that once gave a silently wrong result: each is now refused or honoured."""
from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from cicfw.benchmark.suite import build_suite, make_backend
from cicfw.core.errors import ConfigError

TOWN = Path(__file__).parent / "data" / "bench_town.yaml"


@pytest.mark.parametrize("second", ["copy", "builtin"])
def test_two_towns_of_one_name_are_refused(tmp_path: Path, second: str) -> None:
    """Episodes are keyed <town>/<weather>/<pair> by the town's name (a file's stem): two towns of one name
    would share keys, so one episode's trajectory and map would be the other's."""
    first = tmp_path / "a" / "town_b.yaml"
    first.parent.mkdir()
    shutil.copy(TOWN, first)
    other = str(shutil.copy(TOWN, tmp_path / "town_b.yaml")) if second == "copy" else "town_b"
    with pytest.raises(ConfigError) as err:
        build_suite(make_backend(None), [str(first), other], ["ClearNoon"], training_towns=["town_a"], limit=1)
    assert err.value.key == "suite.towns" and err.value.value == other


def test_towns_of_distinct_names_are_driven(tmp_path: Path) -> None:
    first = Path(shutil.copy(TOWN, tmp_path / "mine.yaml"))
    eps = build_suite(make_backend(None), [str(first), "town_b"], ["ClearNoon"], training_towns=["mine"], limit=1)
    assert len({e.key for e in eps}) == len(eps) == 2


def _ckpt(folder: Path, *names: str) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        (folder / name).write_bytes(b"x")


def test_a_run_folder_means_its_own_checkpoint_not_a_nested_run(tmp_path: Path) -> None:
    """A run trained in a folder inside another run's: ``checkpoint=<outer run>`` is the outer run's
    ``last.ckpt``, never the nested run's best checkpoint."""
    from cicfw.model.checkpoint import resolve_checkpoint

    run = tmp_path / "run"
    _ckpt(run / "checkpoints", "last.ckpt")
    _ckpt(run / "nested" / "checkpoints", "epoch000-mae0.2771.ckpt", "last.ckpt")
    assert resolve_checkpoint(run) == (run / "checkpoints" / "last.ckpt").resolve()
    _ckpt(run / "checkpoints", "epoch001-mae0.2000.ckpt")
    assert resolve_checkpoint(run) == (run / "checkpoints" / "epoch001-mae0.2000.ckpt").resolve()


def test_a_folder_above_several_runs_is_refused(tmp_path: Path) -> None:
    from cicfw.model.checkpoint import CheckpointError, resolve_checkpoint

    _ckpt(tmp_path / "day" / "a" / "checkpoints", "epoch000-mae0.3000.ckpt", "last.ckpt")
    _ckpt(tmp_path / "day" / "b" / "checkpoints", "last.ckpt")
    with pytest.raises(CheckpointError) as err:
        resolve_checkpoint(tmp_path / "day")
    assert err.value.key == "checkpoint" and err.value.value == tmp_path / "day"
    assert resolve_checkpoint(tmp_path / "day" / "b") == (tmp_path / "day" / "b" / "checkpoints" / "last.ckpt").resolve()
    assert resolve_checkpoint(tmp_path / "day" / "a" / "checkpoints").name == "epoch000-mae0.3000.ckpt"
