"""A resume refused before it trains leaves its run folder as it was: the metrics the earlier segments logged
(``csv/metrics.csv``) are kept aside only once the run is sure to train, so a refusal finds them in place."""
from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import pytest

from conftest import TINY_TRAIN, run_app_in_process, train_tiny_run, write_tiny_dataset

pytestmark = pytest.mark.slow  # trains, then runs the app


def _files(folder: Path) -> dict[str, str]:
    """Every file under ``folder``: its relative path -> the MD5 of its bytes."""
    return {str(p.relative_to(folder)): hashlib.md5(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A tiny trained run (one epoch): a folder holding ``csv/metrics.csv`` and ``checkpoints/last.ckpt``."""
    return train_tiny_run(tmp_path_factory.mktemp("refused_resume"), *TINY_TRAIN, "trainer.limit_train_batches=1")


def _other_data(tmp_path: Path) -> tuple[str, list[str]]:
    """Other files than the run trained on, without ``resume_on_other_data``: refused as other data."""
    return str(write_tiny_dataset(tmp_path / "other", n_files=4, n=32, seed=5)), []


def _collected_with_another_config(tmp_path: Path) -> tuple[str, list[str]]:
    """A folder holding a dataset collected with another config, to collect into: refused by the collector."""
    folder = tmp_path / "collected"
    folder.mkdir()
    (folder / "dataset_metadata.json").write_text(json.dumps({"config_hash": "another", "seed": 0}))
    return str(folder), ["data=sim_default", "resume_on_other_data=true"]


def _validation_beyond_the_epoch(tmp_path: Path) -> tuple[str, list[str]]:
    """The run's own data, validated every 1000 batches of a 1-batch epoch: Lightning refuses it only in fit."""
    return "", ["trainer.val_check_interval=1000"]


@pytest.mark.parametrize("other", [_other_data, _collected_with_another_config, _validation_beyond_the_epoch])
def test_a_refused_resume_leaves_the_run_folder_byte_for_byte(trained, tmp_path, other):
    run = tmp_path / "run"
    shutil.copytree(trained["run"], run)
    assert (run / "csv" / "metrics.csv").is_file()
    before = _files(run)
    path, extra = other(tmp_path)
    path = path or str(trained["data"])
    proc = run_app_in_process("cicfw.train", *TINY_TRAIN, "trainer.limit_train_batches=1", *extra,
                              f"data.path={path}", "trainer.max_epochs=4", f"hydra.run.dir={run}",
                              f"ckpt_path={run / 'checkpoints' / 'last.ckpt'}")
    named = path if "trainer.val_check_interval=1000" not in extra else "trainer.val_check_interval"
    assert proc.returncode == 2 and named in proc.stderr.splitlines()[-1], proc.stderr[-2000:]  # refused, naming it
    assert _files(run) == before  # names and bytes: csv/metrics.csv still there, no metrics.1.csv
