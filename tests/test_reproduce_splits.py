"""``python -m cicfw.reproduce``: every seed's train/validation split of the collected dataset is made right
after the collection, before any cell trains; a seed whose split cannot train (here: its train split holds
no 'right' sample) is refused in one line naming the seed, what is missing and what to do, instead of
failing every row's cell of that seed after the cells of the other seeds trained."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

from cicfw.data.frames import load_frames, split_by_episode
from cicfw.reproduction import app as reproduce
from cicfw.testing import write_tiny_dataset

pytestmark = pytest.mark.slow  # runs the reproduce app (without collecting or training)


class Trained(Exception):
    """Raised where a cell would train."""


@pytest.fixture
def smoke_data(tmp_path, monkeypatch) -> Path:
    """The smoke budget's dataset, written here: six episodes (one file each), 'right' in one only."""
    import cicfw.train.app

    monkeypatch.setenv("CICFW_CACHE", str(tmp_path / "cache"))
    data = tmp_path / "cache" / "datasets" / "smoke"
    write_tiny_dataset(data, n_files=5, n=16, commands=(2, 3, 5))
    (data / "data_00000.h5").rename(data / "data_00005.h5")
    write_tiny_dataset(data, n_files=1, n=16, seed=1, commands=(2, 3, 4, 5))  # data_00000.h5: the only 'right'
    monkeypatch.setattr(cicfw.train.app, "ensure_data", lambda data_cfg: None)  # collected: the files above
    monkeypatch.setattr(reproduce, "ensure_data", lambda data_cfg: None)  # the app imported it by name

    def train(*args, **kwargs):
        raise Trained("a cell went on to train")

    monkeypatch.setattr(reproduce, "_train_and_drive", train)
    monkeypatch.setattr(sys, "argv", list(sys.argv))  # main hands Hydra its sweep through sys.argv
    return data


def _seeds(data: Path) -> tuple[list[int], list[int]]:
    """Seeds among 0..9 whose split trains, and those whose train split lacks 'right' (as the smoke budget
    reads the data: |steer| <= 0.8, every camera, 30% of the episodes validate)."""
    frames = load_frames(str(data), 0.8, 0.15, (0, 1, 2))
    ok, bad = [], []
    for seed in range(10):
        try:
            split_by_episode(frames, 0.3, seed)
            ok.append(seed)
        except ValueError as err:
            assert err.value == ["right"], err
            bad.append(seed)
    assert ok and bad, (ok, bad)
    return ok, bad


def test_a_seed_whose_split_cannot_train_is_refused_before_any_cell(smoke_data, tmp_path, capsys):
    ok, bad = _seeds(smoke_data)
    seeds = sorted([ok[0], *bad[:2]])
    out = tmp_path / "results"
    assert reproduce.main(["budget=smoke", "rows=[cil,gtu]", f"seeds=[{','.join(map(str, seeds))}]",
                           f"results_dir={out}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith("cicfw: error: ") and str(smoke_data) in err[0] and "['right']" in err[0], err[0]
    assert f"seed {bad[0]}" in err[0] and f"seed {bad[1]}" in err[0], err[0]  # each seed refused
    assert f"seeds=[{ok[0]}]" in err[0], err[0]  # the override that runs the seeds that split
    assert not (out / "cells").exists() and not (out / "reproduce.json").exists()
    assert not (out / "reproduce.lock").exists()


def test_seeds_that_split_go_on_to_train(smoke_data, tmp_path):
    ok, _ = _seeds(smoke_data)
    out = tmp_path / "results"
    # every cell "fails" at its training (the stand-in raises): the app got past the split check to the cells
    assert reproduce.main(["budget=smoke", "rows=[cil]", f"seeds=[{ok[0]}]", f"results_dir={out}"]) == 1
    assert "Trained: a cell went on to train" in (out / "cells" / "cil" / f"seed{ok[0]}" / "cell.json").read_text()


def test_finished_cells_are_not_checked(smoke_data, tmp_path):
    """A seed whose cells all finished trains nothing: its split is not asked for."""
    _, bad = _seeds(smoke_data)
    out = tmp_path / "results"
    done = out / "cells" / "cil" / f"seed{bad[0]}" / "cell.json"
    done.parent.mkdir(parents=True)
    done.write_text('{"row": "cil", "seed": %d, "status": "ok", "episodes": {}}' % bad[0])
    reproduce.check_splits(reproduce.compose_plan(["budget=smoke", "rows=[cil]"]), ["cil"], [bad[0]],
                           {f"cil/seed{bad[0]}"})
    with pytest.raises(reproduce.ReproduceError) as err:
        reproduce.check_splits(reproduce.compose_plan(["budget=smoke", "rows=[cil]"]), ["cil"], [bad[0]])
    assert (err.value.key, err.value.value) == ("seeds", [bad[0]])
