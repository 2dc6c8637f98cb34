"""Every value checked before work starts: the checkpoint's monitor, the augmentation ranges and the
batches per epoch are refused by key before any data; a multirun whose job failed ends in one line,
not a traceback; a disk that fills while evaluate writes its pictures is one line and no torn file."""
from __future__ import annotations

import csv
import errno
import os
from pathlib import Path

import pytest

import cicfw.benchmark.journal
import cicfw.core.files
from cicfw.benchmark.app import OutputWriteError, evaluate_policy
from cicfw.train.app import make_datamodule, train
from conftest import compose_train, fill_the_disk_for_pictures, run_app_in_process, write_tiny_dataset

BASE = ("data=cil_hdf5", "data.batch_size=8", "data.val_batch_size=8", "progress_bar=false")
TOWN = str(Path(__file__).parent / "data" / "bench_town.yaml")


def _cfg(tmp_path: Path, *overrides: str):
    return compose_train(*BASE, f"data.path={tmp_path}/data", *overrides)


def _refused(tmp_path: Path, *overrides: str) -> str:
    with pytest.raises(ValueError) as err:
        train(_cfg(tmp_path, *overrides), tmp_path / "run")
    text = str(err.value)
    assert "\n" not in text
    return text


@pytest.mark.parametrize("overrides, start", [
    (["optimized_metric=val/stear_mae"], "optimized_metric=val/stear_mae is not a metric the model logs; did you "
                                         "mean 'val/steer_mae'? choose one of val/loss, val/steer_mae,"),
    (["optimized_metric=closed_loop/success"], "optimized_metric=closed_loop/success is measured after training"),
    (["head=softmax", "optimized_metric=val/bin_acc"], "optimized_metric=val/bin_acc is higher-is-better"),
])
def test_an_optimized_metric_the_model_does_not_log_is_refused_before_any_data(tmp_path, no_data, overrides, start):
    text = _refused(tmp_path, *overrides)
    assert text.startswith(start), text
    assert "train/steer_mae" in text


@pytest.mark.parametrize("augment, start", [
    ("{add: 5}", "data.augment.add must be a range [low, high] of two numbers"),
    ("{coarse_size: [0, 0], p_coarse_dropout: 1}", "data.augment.coarse_size must be a range [low, high] with low "
                                                   "<= high, each a size in (0, 1]"),
    ("{multiply: [1.2, 0.8]}", "data.augment.multiply must be a range [low, high] with low <= high"),
    ("{dropout_fraction: [0, 2]}", "data.augment.dropout_fraction must be a range"),
    ("{blur_sigma: [-1, 1]}", "data.augment.blur_sigma must be a range"),
    ("{noise_std: [0, abc]}", "data.augment.noise_std must be a range [low, high] of two numbers"),
    ("{p_blur: abc}", "data.augment.p_blur is a probability in [0, 1], got 'abc'"),
])
def test_a_bad_augmentation_range_is_refused_by_key_before_any_data(tmp_path, no_data, augment, start):
    text = _refused(tmp_path, f"data.augment={augment}")
    assert text.startswith(start), text


@pytest.mark.parametrize("value", ["0", "-1"])
def test_batches_per_epoch_other_than_null_or_a_positive_integer_is_refused(tmp_path, no_data, value):
    text = _refused(tmp_path, f"data.batches_per_epoch={value}")
    assert text.startswith("data.batches_per_epoch") and "null" in text, text  # not the sampler's len()


@pytest.mark.parametrize("value", ["1.5", "true", "abc"])
def test_batches_per_epoch_of_another_type_is_refused_while_composing(value):
    """Not a whole number: the schema (CILDataModule's ``int | None``) refuses it before the app runs."""
    from hydra.errors import HydraException

    from cicfw.core.config_checks import config_error

    with pytest.raises(HydraException) as err:
        compose_train(f"data.batches_per_epoch={value}")
    refused = config_error(err.value)
    assert (refused.kind, refused.key) == ("wrong type", "data.batches_per_epoch"), refused


@pytest.mark.parametrize("value", ["null", "1", "7"])
def test_batches_per_epoch_null_or_a_positive_integer_passes(tmp_path, value):
    make_datamodule(_cfg(tmp_path, f"data.batches_per_epoch={value}"))


# ---- a multirun with a failing job ---------------------------------------------------------------


@pytest.mark.slow  # trains (the app, run in this process)
def test_a_multirun_with_a_failing_job_ends_in_one_line_and_the_summary_keeps_it(tmp_path):
    data = write_tiny_dataset(tmp_path / "data", n_files=4, n=16)
    sweep = tmp_path / "sweep"
    res = run_app_in_process("cicfw.train", "-m", *BASE, f"data.path={data}", "debug=fast", "speed.compile=false",
                             "data.max_abs_steer=0.8,0.0001", f"hydra.sweep.dir={sweep}", env={"HYDRA_FULL_ERROR": "0"})
    assert res.returncode == 1
    assert "Traceback" not in res.stderr, res.stderr[-3000:]
    errors = [line for line in res.stderr.splitlines() if line.startswith("cicfw:")]
    assert len(errors) == 1, res.stderr[-3000:]
    # a user error: cicfw's line alone, not Hydra's "Error executing job ..." and HYDRA_FULL_ERROR advice
    assert "Error executing job" not in res.stderr and "HYDRA_FULL_ERROR" not in res.stderr, res.stderr[-3000:]
    assert errors[0].startswith("cicfw: error: ") and "job 1" in errors[0], errors[0]  # the job, its override
    assert "data.max_abs_steer=0.0001" in errors[0] and str(sweep / "summary.csv") in errors[0], errors[0]
    assert str(sweep / "1") in errors[0], errors[0]  # where its log is
    with open(sweep / "summary.csv", newline="") as f:
        rows = {r["job"]: r for r in csv.DictReader(f)}
    assert rows["0"]["status"] == "ok" and rows["1"]["status"] == "failed"
    assert "max_abs_steer" in rows["1"]["error"]  # found once its files are read: composing passes it


def test_a_failed_jobs_bug_keeps_hydras_report_and_its_user_error_is_one_line(capsys, monkeypatch):
    """What the sweeper raises for a failed job: a bug's line comes with Hydra's "Error executing job" report,
    a user error's (``UserJobFailed``) alone."""
    from hydra.core.utils import JobReturn, JobStatus
    from omegaconf import OmegaConf

    from cicfw.core.errors import CicfwError
    from cicfw.core.override_hints import JobFailed, OneLineJobFailure, UserJobFailed

    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    config = OmegaConf.create({"hydra": {"job": {"num": 1, "name": "train"}, "runtime": {"output_dir": "/nowhere/1"},
                                         "sweep": {"dir": "/nowhere"}}})
    bug = JobReturn(overrides=["x=1"], status=JobStatus.FAILED, _return_value=RuntimeError("boom"))
    user = JobReturn(overrides=["x=2"], status=JobStatus.FAILED, _return_value=CicfwError("x=2 refused", key="x"))
    for ret in (bug, user):
        OneLineJobFailure().on_job_end(config, ret)
    with pytest.raises(JobFailed) as err:
        bug.return_value
    assert not isinstance(err.value, UserJobFailed) and "RuntimeError" in str(err.value)
    assert "Error executing job" in capsys.readouterr().err
    with pytest.raises(UserJobFailed) as err:
        user.return_value
    assert "job 1 (x=2)" in str(err.value)
    assert "Error executing job" not in capsys.readouterr().err


# ---- a full disk while evaluate writes its pictures ----------------------------------------------


def test_a_full_disk_while_writing_the_pictures_is_one_line_and_leaves_no_torn_file(tmp_path, monkeypatch):
    out = tmp_path / "run"
    spec, suite = {"name": "constant", "steer": 0.0}, {"towns": [TOWN], "weathers": ["ClearNoon"], "limit": 1}
    with monkeypatch.context() as mp:
        fill_the_disk_for_pictures(mp)
        with pytest.raises(OutputWriteError) as err:
            evaluate_policy(spec, suite, {"workers": 1}, out)
    text = str(err.value)
    assert text.startswith(f"could not write '{out}/map_") and "(no space left on the device)" in text, text
    assert "\n" not in text and "drives nothing again" in text
    assert not [p.name for p in out.rglob("*") if p.name.startswith(".") and ".tmp" in p.name]
    assert not list(out.glob("*.png"))
    again = evaluate_policy(spec, suite, {"workers": 1}, out)  # room again: the pictures, nothing driven
    assert again.driven == 0 and list(out.glob("*.png"))


def test_a_full_disk_while_logging_an_episode_is_one_line_and_the_rerun_resumes(tmp_path, monkeypatch):
    """The episode log's write cut short by a full disk: one OutputWriteError line saying what is kept and how to
    go on (not an OSError traceback); with room again the same call drives only the rest."""
    write_all = cicfw.core.files.write_all
    written = []

    def full_after_two(fd, data):
        if os.readlink(f"/proc/self/fd/{fd}").endswith("episodes.jsonl") and len(written) >= 2:
            os.write(fd, bytes(data)[:10])  # a short write, then the disk is full
            raise OSError(errno.ENOSPC, "No space left on device")
        written.append(fd)
        write_all(fd, data)

    out = tmp_path / "run"
    spec, suite = {"name": "constant", "steer": 0.0}, {"towns": [TOWN], "weathers": ["ClearNoon"], "limit": 4}
    with monkeypatch.context() as mp:
        mp.setattr(cicfw.benchmark.journal, "write_all", full_after_two)
        with pytest.raises(OutputWriteError) as err:
            evaluate_policy(spec, suite, {"workers": 1}, out)
    text = str(err.value)
    assert "No space left on device" in text and "2 of 4 episodes" in text and str(out) in text, text
    again = evaluate_policy(spec, suite, {"workers": 1}, out)
    assert again.driven == 2 and again.reused == 2
