"""``cicfw train`` as a hostile user runs it: every mistake refused in one line before the
first batch, Ctrl-C says what is kept, and a full disk never leaves a truncated checkpoint behind."""
from __future__ import annotations

import errno
import os
import signal
from pathlib import Path

import pytest
import torch

import cicfw.train.app as train_mod
from cicfw.core.config_checks import SchemaError
from cicfw.core.errors import ConfigError
from cicfw.train.app import train
from conftest import assert_refused, compose_train, run_app_in_process, write_tiny_dataset

pytestmark = pytest.mark.slow  # trains, collects, drives or runs an app (pytest -m "not slow" skips it)

BASE = ("data=cil_hdf5", "data.batch_size=8", "data.val_batch_size=8", "progress_bar=false")
TOWN = str(Path(__file__).parent / "data" / "bench_town.yaml")


def train_app(*args: str):
    """``python -m cicfw.train args``, run in this process (``run_app_in_process``)."""
    return run_app_in_process("cicfw.train", *args, env={"HYDRA_FULL_ERROR": "0"})


def _cfg(tmp_path: Path, *overrides: str):
    return compose_train(*BASE, f"data.path={tmp_path}/data", *overrides)


def _one_line(err: pytest.ExceptionInfo) -> str:
    text = str(err.value)
    assert "\n" not in text, text
    return text


# ---- unknown top-level keys -----------------------------------------------------------------------


@pytest.mark.parametrize("override, key, hint", [  # hint: the key it suggests, if any
    ("+foo=1", "foo", None),
    ("+evaluate_aftr=true", "evaluate_aftr", "'evaluate_after'"),
])
def test_an_unknown_top_level_key_is_refused_before_any_data(tmp_path, no_data, override, key, hint):
    with pytest.raises(ValueError) as err:
        train(_cfg(tmp_path, override), tmp_path / "run")
    assert err.value.key == key and f"'{key}'" in _one_line(err), str(err.value)
    assert hint is None or hint in str(err.value)
    assert "trainer" in str(err.value) and "seed" in str(err.value)  # the keys accepted


# ---- the evaluation's config, checked before the first batch --------------------------------------


@pytest.mark.parametrize("overrides, named", [  # named: what the line must name (the key and value inside)
    (["suite.towns=[town_z]"], ["town_z"]),
    (["suite.limit=0"], ["suite.limit", "0"]),
    (["suite.towns=[town_a"], ["suite.towns=[town_a"]),
    (["suite=nosuch"], ["suite", "nosuch", "junctions, single_turn"]),
    (["video=[nosuch]"], ["video", "nosuch"]),
])
def test_bad_evaluate_overrides_are_refused_before_the_first_batch(tmp_path, no_data, overrides, named):
    cfg = _cfg(tmp_path, "evaluate_after=true", f"evaluate_overrides=[{','.join(repr(o) for o in overrides)}]")
    with pytest.raises(ValueError) as err:
        train(cfg, tmp_path / "run")
    assert err.value.key == "evaluate_overrides" and _one_line(err).startswith("evaluate_overrides: ")
    assert all(n in str(err.value) for n in named), str(err.value)


@pytest.mark.parametrize("overrides, kind, key", [
    (["suite.foo=1"], "unknown key", "suite.foo"),
    (["+foo=1"], "unknown key", "foo"),
    (["runner.workers=0"], "wrong type", "runner.workers"),
    (["+runner.foo=1"], "unknown key", "runner.foo"),
    (["+policy.nosuch=1"], "unknown key", "policy.nosuch"),
    (["seed=abc"], "wrong type", "seed"),
])
def test_evaluate_overrides_the_schema_refuses_are_refused_before_the_first_batch(tmp_path, no_data, overrides,
                                                                                  kind, key):
    cfg = _cfg(tmp_path, "evaluate_after=true", f"evaluate_overrides=[{','.join(repr(o) for o in overrides)}]")
    with pytest.raises(SchemaError) as err:
        train(cfg, tmp_path / "run")
    assert (err.value.kind, err.value.key) == (kind, key), str(err.value)
    assert _one_line(err).startswith("evaluate_overrides: ")


def test_evaluate_overrides_without_evaluate_after_are_refused_before_any_run_folder(tmp_path, no_data):
    """``evaluate_overrides`` on the command line set the evaluation that only ``evaluate_after=true`` runs:
    without it they were silently unused."""
    res = train_app(*BASE, f"data.path={tmp_path}/data", 'evaluate_overrides=["suite.limit=1"]',
                    f"hydra.run.dir={tmp_path / 'run'}")
    line = assert_refused(res, "evaluate_overrides", "suite.limit=1")
    assert "evaluate_after=true" in line, line
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("overrides, refused", [
    (['evaluate_overrides=["suite.limit=1"]'], True),
    (['++evaluate_overrides=["suite.limit=1"]', "experiment=paper_cil"], True),
    (['evaluate_overrides=["suite.limit=1"]', "evaluate_after=true"], False),
    (["experiment=paper_cil"], False),  # the experiment's own, for when the evaluation is asked for
    (["experiment=paper_cil", "evaluate_after=false"], False),
    (["evaluate_overrides=[]"], False),
])
def test_only_the_command_line_s_evaluate_overrides_need_evaluate_after(overrides, refused):
    """What a multirun checks of each job (its config with Hydra's record of the job's overrides)."""
    from hydra import compose, initialize_config_module

    from cicfw.core.errors import ConfigError
    from cicfw.train.app import check_config

    with initialize_config_module("cicfw.conf", version_base="1.3"):
        cfg = compose("train", overrides=[*overrides, "data=cil_hdf5", "data.path=none"], return_hydra_config=True)
    if not refused:
        check_config(cfg)
        return
    with pytest.raises(ConfigError) as err:
        check_config(cfg)
    assert (err.value.key, err.value.value) == ("evaluate_overrides", ["suite.limit=1"])


def test_good_evaluate_overrides_pass_the_check():
    from cicfw.benchmark.app import check_evaluation_overrides

    check_evaluation_overrides([f"suite.towns=[{TOWN}]", "suite.limit=1", "runner.workers=2", "video=[0]"])
    check_evaluation_overrides(["suite=single_turn", "policy.device=cpu"])


# ---- tracebacks where one line belongs -----------------------------------------------------------


@pytest.mark.parametrize("override, key", [
    ("model.lr=abc", "model.lr"),
    ("model.betas=abc", "model.betas"),
    ("mixer.hidden=wide", "mixer.hidden"),
])
def test_a_value_of_the_wrong_type_is_one_line_before_any_run_folder(tmp_path, override, key):
    """Refused while Hydra composes the config (the schema), so the app writes no run folder at all."""
    proc = train_app(override, f"hydra.run.dir={tmp_path}/run")
    assert_refused(proc, key, override.split("=", 1)[1])
    assert "HYDRA_FULL_ERROR" not in proc.stderr
    assert not (tmp_path / "run").exists()


def test_a_folder_of_your_own_cil_files_without_data_cil_hdf5_names_it(tmp_path):
    data = write_tiny_dataset(tmp_path / "mine")
    cfg = compose_train("data.batch_size=8", "data.val_batch_size=8", f"data.path={data}", "progress_bar=false")
    with pytest.raises(ValueError) as err:
        train(cfg, tmp_path / "run")
    text = _one_line(err)
    assert f"data.path={data}" in text and "6" in text, text  # the key, the value, how many files
    assert f"python -m cicfw.train data=cil_hdf5 data.path={data}" in text  # the command that trains on them
    assert not (data / "dataset_metadata.json").exists()  # nothing collected into the user's folder


# ---- a full disk while saving a checkpoint -------------------------------------------------------


@pytest.fixture
def full_disk(monkeypatch):
    """``full_disk(folder)``: the filesystem holding ``folder`` is full, and the system's temporary
    folder lives on another one (as /tmp on tmpfs does): any write into ``folder`` stores its first
    100 bytes and then fails with ENOSPC, and a rename into ``folder`` from elsewhere fails with EXDEV
    (so it is copied, and the copy hits the full disk)."""
    real_write, real_sendfile, real_rename = os.write, os.sendfile, os.rename
    state = {"folder": None}

    def inside(fd: int) -> bool:
        return state["folder"] is not None and os.readlink(f"/proc/self/fd/{fd}").startswith(state["folder"])

    def write(fd, data):
        if inside(fd):
            real_write(fd, bytes(data)[:100])
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(fd, data)

    def sendfile(out_fd, in_fd, offset, count):
        if inside(out_fd):
            real_sendfile(out_fd, in_fd, offset, min(count, 100))
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_sendfile(out_fd, in_fd, offset, count)

    def rename(src, dst, *a, **k):
        if state["folder"] and str(dst).startswith(state["folder"]) and not str(src).startswith(state["folder"]):
            raise OSError(errno.EXDEV, "Invalid cross-device link")
        return real_rename(src, dst, *a, **k)

    monkeypatch.setattr(os, "write", write)
    monkeypatch.setattr(os, "sendfile", sendfile)
    monkeypatch.setattr(os, "rename", rename)

    def fill(folder: Path) -> None:
        state["folder"] = str(Path(folder).resolve())

    return fill


def test_a_full_disk_while_saving_a_checkpoint_is_one_line_and_leaves_no_truncated_file(tmp_path, full_disk):
    data = write_tiny_dataset(tmp_path / "data")
    run = tmp_path / "run"
    ckpts = run / "checkpoints"
    ckpts.mkdir(parents=True)
    (ckpts / "last.ckpt").write_bytes(b"the previous last.ckpt")
    cfg = compose_train(*BASE, f"data.path={data}", "trainer.max_epochs=1", "trainer.limit_train_batches=1",
                        "trainer.limit_val_batches=1", "speed.compile=false")
    full_disk(ckpts)
    with pytest.raises(ValueError) as err:
        train(cfg, run, claim=False)  # a folder its caller holds: the earlier last.ckpt is written over
    text = _one_line(err)
    assert str(ckpts) in text and "ckpt_path=" in text, text  # the folder, and the override that resumes
    assert (ckpts / "last.ckpt").read_bytes() == b"the previous last.ckpt"  # intact, not half overwritten
    assert sorted(p.name for p in ckpts.iterdir()) == ["last.ckpt"]  # no truncated file, no temporary left


def test_checkpoints_are_whole_files_readable_by_others(tmp_path):
    data = write_tiny_dataset(tmp_path / "data")
    cfg = compose_train(*BASE, f"data.path={data}", "trainer.max_epochs=1", "trainer.limit_train_batches=1",
                        "trainer.limit_val_batches=1", "speed.compile=false")
    old = os.umask(0o022)
    try:
        train(cfg, tmp_path / "run")
    finally:
        os.umask(old)
    files = sorted((tmp_path / "run" / "checkpoints").iterdir())
    assert [p.name for p in files if p.name == "last.ckpt"] and len(files) == 2
    for p in files:
        assert p.stat().st_mode & 0o777 == 0o644, p
        assert torch.load(p, map_location="cpu", weights_only=True)["epoch"] == 0


def test_ctrl_c_during_training_names_the_checkpoint_to_resume_from(tmp_path, monkeypatch):
    """Lightning's graceful shutdown ends in ``sys.exit(1)``: train says what is kept instead."""
    import signal

    from lightning.pytorch.callbacks import Callback

    from cicfw.core.errors import Interrupted

    class CtrlC(Callback):
        def on_train_batch_start(self, trainer, *args):
            if trainer.current_epoch == 1:
                raise KeyboardInterrupt

    real = train_mod.build_callbacks
    monkeypatch.setattr(train_mod, "build_callbacks", lambda cfg, run_dir: [*real(cfg, run_dir), CtrlC()])
    data = write_tiny_dataset(tmp_path / "data")
    cfg = compose_train(*BASE, f"data.path={data}", "trainer.max_epochs=3", "trainer.limit_train_batches=1",
                        "trainer.limit_val_batches=1", "speed.compile=false")
    handler = signal.getsignal(signal.SIGINT)
    try:
        with pytest.raises(Interrupted) as err:
            train(cfg, tmp_path / "run")
    finally:
        signal.signal(signal.SIGINT, handler)  # Lightning ignores Ctrl-C after its shutdown
    last = tmp_path / "run" / "checkpoints" / "last.ckpt"
    assert str(err.value) == (f"during training epoch 2: the finished epochs are kept in {last.parent}; "
                              f"resume with ckpt_path={last}")
    assert torch.load(last, map_location="cpu", weights_only=True)["epoch"] == 0


# ---- the app: Ctrl-C, an unusable run folder -----------------------------------------------------


def _errors(proc) -> list[str]:
    assert "Traceback" not in proc.stderr, proc.stderr[-3000:]
    return [line for line in proc.stderr.splitlines() if line.startswith("cicfw:")]


def test_ctrl_c_during_the_compile_warm_up_is_one_line(tmp_path, monkeypatch):
    """The app run in this process (its handlers are put back after), Ctrl-C sent while the training step
    compiles: a real SIGINT to this process, as the neighbouring Ctrl-C test does in-process."""
    import time

    import cicfw.model.speed as speed

    def warm_up(model, batch_size):
        os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C while the training step compiles
        time.sleep(30)

    monkeypatch.setattr(speed, "warm_up", warm_up)
    data = write_tiny_dataset(tmp_path / "data")
    proc = train_app(*BASE, f"data.path={data}", "speed.compile=true", "debug=fast", f"hydra.run.dir={tmp_path}/out")
    assert proc.returncode == 130, proc.stderr[-3000:]
    assert _errors(proc) == ["cicfw: interrupted; during the compile warm-up, before the first training step: "
                             "nothing to keep yet (what was compiled is cached), run the same command again"]


def read_only_in_process(tmp_path: Path, monkeypatch, module: str, *args: str):
    """``python -m <module> args`` in this process with ``tmp_path/ro`` read-only (a read-only mount): ``os.mkdir``
    and ``os.open`` refuse it while the app runs (``monkeypatch`` puts them back)."""
    ro = str(tmp_path / "ro")
    (tmp_path / "ro").mkdir()
    real_mkdir, real_open = os.mkdir, os.open

    def refuse(path):
        if os.path.abspath(os.fspath(path)).startswith(ro + os.sep):
            raise PermissionError(errno.EACCES, "Permission denied", os.fspath(path))

    def mkdir(path, *a, **k):
        refuse(path)
        return real_mkdir(path, *a, **k)

    def open_(path, *a, **k):
        refuse(path)
        return real_open(path, *a, **k)

    monkeypatch.setattr(os, "mkdir", mkdir)
    monkeypatch.setattr(os, "open", open_)
    return run_app_in_process(module, *args, env={"HYDRA_FULL_ERROR": "0"})


def test_a_read_only_run_folder_is_one_line(tmp_path, monkeypatch):
    proc = read_only_in_process(tmp_path, monkeypatch, "cicfw.train", *BASE, f"data.path={tmp_path}/data",
                                f"hydra.run.dir={tmp_path}/ro/run")
    assert_refused(proc, "hydra.run.dir", f"{tmp_path}/ro/run")


def test_a_300_character_run_name_is_one_line(tmp_path):
    name = "n" * 300
    proc = train_app(*BASE, f"data.path={tmp_path}/data", f"hydra.run.dir={tmp_path}/{name}")
    assert "255" in assert_refused(proc, "hydra.run.dir", name[:20])  # the filesystem's limit
    assert not (tmp_path / name[:255]).exists()
    proc = train_app(*BASE, f"data.path={tmp_path}/data", f"hydra.run.dir={tmp_path}/run", f"hydra.job.name={name}")
    assert "255" in assert_refused(proc, "hydra.job.name", name[:20])


# ---- values of the wrong type or range, refused by name before any data (bad-input sweep) -------------


@pytest.mark.parametrize("overrides, key", [
    # unions the schema leaves open (Any): checked by what Lightning takes (cicfw/train/schema.py), or its own error
    (["trainer.max_time=1.5"], "trainer.max_time"),
    (["trainer.max_time=[1]"], "trainer.max_time"),
    (["trainer.max_time=1:00"], "trainer"),
    (["trainer.deterministic=sure"], "trainer.deterministic"),
    (["speed.compile=maybe"], "speed.compile"),
    (["trainer.gradient_clip_algorithm=1.5"], "trainer"),
    (["keep_epoch_checkpoints=[0,2]"], "keep_epoch_checkpoints"),
    (["data.batch_size=0"], "data.batch_size"),
    (["data.val_batch_size=0"], "data.val_batch_size"),
    (["data.num_workers=-1"], "data.num_workers"),  # the DataLoader's traceback, after the files were read
    (["data.balanced=false", "data.batches_per_epoch=2"], "data.batches_per_epoch"),  # was ignored: a full pass
    (["data.cameras=5"], "data.cameras"),
    (["data.val_cameras=[]"], "data.val_cameras"),
    (["data.cameras=[5]"], "data.val_cameras"),
])
def test_a_bad_value_is_refused_by_its_key_before_any_data(tmp_path, no_data, overrides, key):
    with pytest.raises(ValueError) as err:
        train(_cfg(tmp_path, *overrides), tmp_path / "run")
    assert _one_line(err).startswith(key), str(err.value)
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("key", ["cameras", "val_cameras"])
def test_a_camera_id_listed_twice_is_refused_by_its_key_before_any_data(tmp_path, no_data, key):
    with pytest.raises(ConfigError) as err:
        train(_cfg(tmp_path, f"data.{key}=[0,0]"), tmp_path / "run")
    assert (err.value.key, list(err.value.value)) == (f"data.{key}", [0, 0])
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("override, key", [
    ("speed.compile=maybe", "speed.compile"),
    ("trainer.compile=true", "speed.compile"),  # the switch's key under trainer: the line names the speed node's
    ("trainer.deterministic=sure", "trainer.deterministic"),
    ("trainer.max_time=5", "trainer.max_time"),
])
def test_the_app_refuses_a_speed_or_trainer_value_in_one_line_without_a_run_folder(tmp_path, override, key):
    proc = train_app(*BASE, f"data.path={tmp_path}/data", override, f"hydra.run.dir={tmp_path}/run")
    assert proc.returncode == 2, proc.stderr[-3000:]
    errors = _errors(proc)
    assert len(errors) == 1 and key in errors[0], errors
    assert not (tmp_path / "run").exists()


def test_trainer_values_of_every_accepted_type_pass_the_check(tmp_path):
    cfg = _cfg(tmp_path, "trainer.max_epochs=null", "trainer.deterministic=warn", "trainer.limit_train_batches=0.5",
               "trainer.fast_dev_run=2", "trainer.max_time=00:00:01:00", "trainer.devices=1",
               "trainer.gradient_clip_algorithm=norm")
    kwargs = train_mod.trainer_kwargs(cfg)
    assert train_mod.trainer_kwargs(_cfg(tmp_path, "trainer.max_time={days:1,hours:2}"))["max_time"] == \
        {"days": 1, "hours": 2}
    assert kwargs["deterministic"] == "warn" and kwargs["max_epochs"] is None and kwargs["fast_dev_run"] == 2
    assert train_mod.EpochCheckpoints(tmp_path, _cfg(tmp_path, "keep_epoch_checkpoints=[1,3]").keep_epoch_checkpoints,
                                      3).epochs == {1, 3}


def test_cameras_the_default_data_does_not_record_are_refused_before_collecting(tmp_path, no_data):
    cfg = compose_train("data=sim_default", f"data.path={tmp_path}/sim", "+data.collect.cameras=[centre]",
                        "data.cameras=[1,2]", "data.val_cameras=[1]", "progress_bar=false")
    with pytest.raises(ValueError) as err:
        train(cfg, tmp_path / "run")
    assert "data.cameras=[1, 2]" in _one_line(err) and "collect.cameras" in str(err.value)  # value, and the key
    assert not (tmp_path / "sim").exists()


@pytest.mark.parametrize("overrides, message", [  # message: the key=value the line starts with
    (["data.cameras=[5]", "data.val_cameras=null"], "data.cameras=[5]"),
    (["data.cameras=null", "data.val_cameras=[5]"], "data.val_cameras=[5]"),
])
def test_cameras_the_files_do_not_hold_are_named_not_zero_episodes(tmp_path, overrides, message):
    """``data.cameras=[5]`` on a folder of 6 files said "the data holds 0 episode(s) ... at least 2 files"."""
    write_tiny_dataset(tmp_path / "data")
    with pytest.raises(ValueError) as err:
        train(_cfg(tmp_path, *overrides), tmp_path / "run")
    assert _one_line(err).startswith(message), str(err.value)
    assert "episode" not in str(err.value)
    assert not (tmp_path / "run" / "checkpoints").exists()
