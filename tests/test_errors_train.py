"""One clear line for every user error of ``cicfw train``, each checked before
any image is collected or read, and resuming that loads checkpoints with ``weights_only=True``.

``train()`` raises the ``ValueError`` / ``FileNotFoundError`` whose message the app prints as
``cicfw: error: <message>`` (tests/test_train.py checks that wrapper on the command line)."""
from __future__ import annotations

from pathlib import Path

import pytest
import torch

from cicfw.benchmark.suite import check_names
from cicfw.data.frames import load_frames, split_by_episode
from cicfw.core.config_checks import SchemaError
from cicfw.core.errors import CicfwError, ConfigError
from cicfw.model.module import CICModule
from cicfw.train.app import build_model, build_trainer, check_resume_checkpoint, train
from conftest import compose_train, damaged_checkpoints, misfit_counts, run_app_in_process, write_tiny_dataset

pytestmark = pytest.mark.slow  # trains, collects, drives or runs an app (pytest -m "not slow" skips it)

BASE = ("data=cil_hdf5", "data.batch_size=8", "data.val_batch_size=8", "progress_bar=false")


def _cfg(tmp_path: Path, *overrides: str):
    return compose_train(*BASE, f"data.path={tmp_path}/data", *overrides)


@pytest.mark.parametrize("overrides, error, key, value", [
    (["trainer.max_epochs=-2"], CicfwError, "trainer.max_epochs", -2),
    (["trainer.limit_train_batches=0"], ConfigError, "trainer.limit_train_batches", 0),  # trains nothing, exit 0
    (["trainer.limit_train_batches=0.0"], ConfigError, "trainer.limit_train_batches", 0.0),
    (["trainer.limit_train_batches=-1"], ConfigError, "trainer.limit_train_batches", -1),
    (["trainer.limit_train_batches=2.5"], ConfigError, "trainer.limit_train_batches", 2.5),
    (["trainer.precision=17"], CicfwError, "trainer", None),  # Lightning's own refusal, named by its node
    (["+mixer.foo=1"], SchemaError, "mixer.foo", None),  # keys added with +: the schema refuses them here
    (["mixer=gtu", "+mixer.hiden=64"], SchemaError, "mixer.hiden", None),
    (["+mixer.in_dim=64"], SchemaError, "mixer.in_dim", None),
    (["head=hybrid", "+head.foo=1"], SchemaError, "head.foo", None),
    (["+encoder.foo=1"], SchemaError, "encoder.foo", None),
    (["+model.foo=1"], SchemaError, "model.foo", None),
    (["+data.foo=1"], SchemaError, "data.foo", None),
    (["data.batch_size=6"], ConfigError, "data.batch_size", 6),  # values the constructors refuse
    (["data.val_fraction=1.5"], ConfigError, "data.val_fraction", 1.5),
    (["ckpt_path=/nonexistent/last.ckpt"], FileNotFoundError, "ckpt_path", None),
])
def test_each_config_error_is_one_line_before_any_data(tmp_path, no_data, overrides, error, key, value):
    with pytest.raises(error) as err:
        train(_cfg(tmp_path, *overrides), tmp_path / "run")
    text = str(err.value.args[0] if isinstance(err.value, FileNotFoundError) else err.value)
    if isinstance(err.value, CicfwError):
        assert (err.value.key, err.value.value) == (key, value)
    else:
        assert text.startswith(key), text  # a path the user gave, named by its key
    assert "\n" not in text


def test_any_trainer_argument_passes_without_plus(tmp_path):
    cfg = _cfg(tmp_path, "trainer.fast_dev_run=true", "trainer.accumulate_grad_batches=2")
    trainer = build_trainer(cfg, tmp_path / "run")
    assert trainer.fast_dev_run is True and trainer.accumulate_grad_batches == 2
    cfg = _cfg(tmp_path, "trainer=ddp", "trainer.accelerator=cpu", "trainer.devices=1",
               "trainer.precision=32-true", "trainer.limit_val_batches=3")
    assert build_trainer(cfg, tmp_path / "run2").limit_val_batches == 3


@pytest.mark.skipif(torch.cuda.is_available(), reason="fp16 autocast runs on a GPU")
@pytest.mark.parametrize("precision", ["16-mixed", "16"])
def test_fp16_on_a_cpu_is_refused_not_trained_in_bf16(tmp_path, precision):
    """Lightning trains trainer.precision=16-mixed in bf16 on a CPU, with a warning: the run's config and
    checkpoint would name a precision it never used."""
    with pytest.raises(ConfigError) as err:
        build_trainer(_cfg(tmp_path, f"trainer.precision={precision}", "trainer.accelerator=cpu"), tmp_path / "run")
    assert (err.value.key, str(err.value.value)) == ("trainer.precision", precision)
    assert build_trainer(_cfg(tmp_path, "trainer.precision=bf16-mixed"), tmp_path / "run2").precision == "bf16-mixed"


def test_trainer_arguments_take_plus_alike_on_the_command_line(tmp_path):
    """A typed argument with a value (max_epochs), an untyped one with a value (fast_dev_run) and one that is
    null (limit_train_batches) all take ``+trainer.X=`` as ``trainer.X=``."""
    import yaml

    for plus in ("", "+"):
        args = [f"{plus}trainer.max_epochs=3", f"{plus}trainer.fast_dev_run=true", f"{plus}trainer.limit_train_batches=3"]
        run = run_app_in_process("cicfw.train", *args, "--cfg", "job", cwd=tmp_path)
        assert run.returncode == 0, run.stderr[-2000:]
        trainer = yaml.safe_load(run.stdout)["trainer"]
        assert (trainer["max_epochs"], trainer["fast_dev_run"], trainer["limit_train_batches"]) == (3, True, 3)


def test_trainer_argument_from_the_command_line(tmp_path):
    """The whole app: ``trainer.fast_dev_run=true`` (no ``+``) trains one step; a value Lightning refuses
    is one line, and the refused run leaves no run folder behind."""
    data = write_tiny_dataset(tmp_path / "data")
    env = {"HYDRA_FULL_ERROR": "0"}
    common = [*BASE, f"data.path={data}", f"hydra.run.dir={tmp_path}/out"]
    ok = run_app_in_process("cicfw.train", *common, "trainer.fast_dev_run=true", env=env)
    assert ok.returncode == 0, ok.stderr[-2000:]
    assert "`Trainer.fit` stopped: `max_steps=1` reached." in ok.stderr + ok.stdout
    common[-1] = f"hydra.run.dir={tmp_path}/refused/run"
    bad = run_app_in_process("cicfw.train", *common, "trainer.max_epochs=-2", env=env)
    assert bad.returncode == 2
    errors = [line for line in bad.stderr.splitlines() if line.startswith("cicfw:")]
    assert len(errors) == 1 and errors[0].startswith("cicfw: error: trainer") and "max_epochs" in errors[0], errors
    assert "Traceback" not in bad.stderr
    assert not (tmp_path / "refused").exists()  # neither .hydra nor an empty train.log, nor the parent made for it


# ---- checkpoints given to ckpt_path= --------------------------------------------------------------


def _resumable(model, path: Path, **extra) -> Path:
    """A checkpoint with what Lightning's resume reads (state_dict, optimizer and loop state)."""
    torch.save({"state_dict": model.state_dict(), "optimizer_states": [], "lr_schedulers": [], "loops": {},
                "epoch": 0, "global_step": 0, "pytorch-lightning_version": "2.6.0",
                "hyper_parameters": dict(model.hparams), **extra}, path)
    return path


class _RunsCode:
    """Unpickling this calls ``exec``: what a malicious checkpoint does."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return exec, (f"open({str(self.marker)!r}, 'w').close()",)


def test_a_checkpoint_that_would_run_code_is_refused(tmp_path, no_data, monkeypatch):
    marker = tmp_path / "code_ran"
    cfg = _cfg(tmp_path)
    evil = _resumable(build_model(cfg), tmp_path / "evil.ckpt", callbacks=_RunsCode(marker))
    monkeypatch.setenv("TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD", "1")  # torch's opt-out must not matter
    with pytest.raises(ValueError) as err:
        train(_cfg(tmp_path, f"ckpt_path={evil}"), tmp_path / "run")
    assert (err.value.key, str(err.value.value)) == ("ckpt_path", str(evil))
    assert "GLOBAL exec" in str(err.value)  # what it would have run
    assert not marker.exists()
    torch.load(evil, weights_only=False)  # the payload is live: loading it the unsafe way runs it
    assert marker.exists()


def test_bad_checkpoints_each_say_what_is_wrong(tmp_path, no_data):
    cfg = _cfg(tmp_path)
    model = build_model(cfg)
    good = _resumable(model, tmp_path / "good.ckpt")
    assert check_resume_checkpoint(good, model) == str(good)
    truncated = tmp_path / "truncated.ckpt"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    weights = tmp_path / "weights.ckpt"
    torch.save({"state_dict": model.state_dict(), "epoch": 0}, weights)
    other = _resumable(build_model(_cfg(tmp_path, "mixer=gtu")), tmp_path / "gtu.ckpt")
    plain = tmp_path / "plain.pt"
    torch.save(model.state_dict(), plain)
    cases = {  # each file, and what the line must name besides ckpt_path and the file
        truncated: [], weights: [], plain: ["'state_dict'"], tmp_path: [f"{tmp_path}/checkpoints/last.ckpt"],
        other: ["cil/gtu/regression", "cil/independent/regression"],  # the two models
    }
    for path, named in cases.items():
        with pytest.raises(ValueError) as err:
            train(_cfg(tmp_path, f"ckpt_path={path}"), tmp_path / "run")
        assert (err.value.key, str(err.value.value)) == ("ckpt_path", str(path)), str(err.value)
        assert all(n in str(err.value) for n in named) and "\n" not in str(err.value), str(err.value)


def test_resuming_a_damaged_checkpoint_names_the_weights_not_another_model(tmp_path):
    """Weights that do not fit the model the checkpoint itself records: no options would resume it."""
    model, files = damaged_checkpoints(tmp_path)
    for name, (path, counts, key) in files.items():
        with pytest.raises(CicfwError) as err:
            check_resume_checkpoint(path, model)
        text = str(err.value)
        assert (err.value.key, err.value.value) == ("ckpt_path", path), name
        assert misfit_counts(text) == counts and repr(key) in text, text
        assert "edited" in text and "another model" not in text and "options" not in text, text
    gtu = CICModule(mixer="gtu", mixer_kwargs={"hidden": 8})  # an intact checkpoint of another model still says so
    path = tmp_path / "gtu.ckpt"
    torch.save({"state_dict": gtu.state_dict(), "optimizer_states": [], "loops": {},
                "hyper_parameters": dict(gtu.hparams)}, path)
    with pytest.raises(CicfwError) as err:
        check_resume_checkpoint(path, model)
    assert err.value.key == "ckpt_path" and misfit_counts(str(err.value)) == files["other_mixer"][1]
    assert "another model" in str(err.value) and "edited" not in str(err.value)


@pytest.mark.parametrize("trained, resumed, key, value", [
    (["head=softmax", "head.n_classes=5", "head.low=-1", "head.high=1", "head.bin_width=0.4"],
     ["head=softmax", "head.n_classes=5", "head.low=-0.9", "head.high=0.9", "head.bin_width=0.36"], "head.low", -0.9),
    (["head=sine", "head.phase_range=0.9"], ["head=sine", "head.phase_range=0.5"], "head.phase_range", 0.5),
    ([], ["model.speed_norm_kmh=80"], "model.speed_norm_kmh", 80.0),
    (["mixer=re"], ["mixer=re", "mixer.R=[[0,0,0,0],[0,0,0,0],[0,0,0,0],[0,0,0,0]]"], "mixer.R", [[0] * 4] * 4),
])
def test_resuming_with_another_input_scale_or_output_encoding_is_refused(tmp_path, no_data, trained, resumed, key,
                                                                          value):
    """Weights of the same shapes, read with another meaning, would train on as neither model."""
    ckpt = _resumable(build_model(_cfg(tmp_path, *trained)), tmp_path / "last.ckpt")
    with pytest.raises(CicfwError) as err:
        train(_cfg(tmp_path, *resumed, f"ckpt_path={ckpt}"), tmp_path / "run")
    assert (err.value.key, err.value.value) == (key, value) and "\n" not in str(err.value)


def test_resuming_with_another_model_whose_weights_fit_is_refused(tmp_path, no_data):
    """A plugin's head or mixer of another name can fit a checkpoint's weights exactly: another model."""
    model = build_model(_cfg(tmp_path))
    ckpt = _resumable(model, tmp_path / "last.ckpt", hyper_parameters={**model.hparams, "head": "tanh"})
    with pytest.raises(CicfwError) as err:
        train(_cfg(tmp_path, f"ckpt_path={ckpt}"), tmp_path / "run")
    assert (err.value.key, err.value.value) == ("head", "regression") and "tanh" in str(err.value)
    binned = _resumable(build_model(_cfg(tmp_path, "head=softmax")), tmp_path / "softmax.ckpt")
    with pytest.raises(CicfwError) as err:  # another binned head may take over, but only with the same bins
        train(_cfg(tmp_path, "head=hybrid", "head.low=-1", "head.high=0.8",
                   f"ckpt_path={binned}"), tmp_path / "run")
    assert (err.value.key, err.value.value) == ("head.low", -1.0)
    assert check_resume_checkpoint(binned, build_model(_cfg(tmp_path, "head=hybrid"))) == str(binned)


def test_a_part_keeps_the_kwargs_it_names_on_resume(tmp_path, no_data, monkeypatch):
    """A mixer (a plugin's attention heads) names the kwargs whose other value would change what its weights do."""
    from cicfw.registry import MIXERS

    ckpt = _resumable(build_model(_cfg(tmp_path, "mixer=gtu")), tmp_path / "last.ckpt")
    other = build_model(_cfg(tmp_path, "mixer=gtu", "mixer.dropout=[0.3,0.0]"))
    assert check_resume_checkpoint(ckpt, other) == str(ckpt)  # dropout may change ...
    monkeypatch.setattr(MIXERS.get("gtu"), "kept_on_resume", ("dropout",))
    with pytest.raises(CicfwError) as err:  # ... unless the mixer says it may not
        check_resume_checkpoint(ckpt, other)
    assert (err.value.key, err.value.value) == ("mixer.dropout", [0.3, 0.0])


def test_resuming_with_another_loss_weight_or_decoder_passes_the_check(tmp_path, no_data):
    """The loss and how steering is read out may change on resume: the weights keep their meaning."""
    model = build_model(_cfg(tmp_path, "head=hybrid", "head.W=10"))
    ckpt = _resumable(model, tmp_path / "last.ckpt")
    other = build_model(_cfg(tmp_path, "head=hybrid", "head.W=5", "head.decode=argmax"))
    assert check_resume_checkpoint(ckpt, other) == str(ckpt)


def test_a_file_that_is_no_pickle_is_not_called_unsafe(tmp_path, no_data):
    """An 11-byte text file was refused as "pickled Python objects ... which could run code"."""
    text = tmp_path / "text.ckpt"
    text.write_text("not a ckpt\n")
    with pytest.raises(ValueError) as err:
        train(_cfg(tmp_path, f"ckpt_path={text}"), tmp_path / "run")
    assert (err.value.key, str(err.value.value)) == ("ckpt_path", str(text))
    assert "UnpicklingError" in str(err.value) and "run code" not in str(err.value)  # not called unsafe
    assert not (tmp_path / "run").exists()


def test_lightning_resumes_with_weights_only(tmp_path, monkeypatch):
    """Lightning's own load of ``ckpt_path`` is asked for ``weights_only=True`` (not torch's default)."""
    from lightning.pytorch.trainer.connectors.checkpoint_connector import _CheckpointConnector

    seen = {}

    class Stop(Exception):
        pass

    def resume_start(self, checkpoint_path=None, weights_only=None):
        seen.update(path=checkpoint_path, weights_only=weights_only)
        raise Stop

    monkeypatch.setattr(_CheckpointConnector, "resume_start", resume_start)
    write_tiny_dataset(tmp_path / "data")
    ckpt = _resumable(build_model(_cfg(tmp_path)), tmp_path / "last.ckpt")
    with pytest.raises(Stop):
        train(_cfg(tmp_path, f"ckpt_path={ckpt}", "debug=fast"), tmp_path / "run")
    assert seen == {"path": str(ckpt), "weights_only": True}


# ---- data ------------------------------------------------------------------------------------------


def test_a_command_absent_from_the_whole_dataset_does_not_suggest_another_split(tmp_path):
    write_tiny_dataset(tmp_path, n_files=4, commands=(2, 3, 5))  # no 'right' anywhere
    frames = load_frames(str(tmp_path))
    with pytest.raises(ValueError) as err:
        split_by_episode(frames, 0.3, 0)
    msg = str(err.value)
    assert "['right']" in msg and "data.max_abs_steer" in msg and "data.cameras" in msg  # the command, the filters
    assert "seed" not in msg and "val_fraction" not in msg


def test_a_missing_town_file_says_no_such_file(tmp_path):
    known = ["town_a", "town_b"]
    missing = str(tmp_path / "my_town.yaml")
    with pytest.raises(ValueError) as err:
        check_names("town", [missing], known, path_ok=True)
    assert err.value.value == missing and "town_a, town_b" in str(err.value)  # the file, and the names known
    with pytest.raises(ValueError) as err:
        check_names("town", ["town_c"], known, path_ok=True)
    assert err.value.value == "town_c" and "town_a, town_b" in str(err.value)
    (tmp_path / "my_town.yaml").write_text("name: my_town\n")
    assert check_names("town", [missing], known, path_ok=True) == [missing]


def test_a_registered_mixer_with_a_required_argument_names_it(tmp_path, no_data, monkeypatch):
    """A plugin's mixer whose argument has no default: the run is refused naming ``mixer.width``."""
    import torch

    from cicfw.model.mixers import Mixer
    from cicfw.registry import MIXERS
    from cicfw.train.schema import part

    class NeedsWidth(Mixer):
        def __init__(self, in_dim: int, out_dim: int, width: int, hidden: int = 8) -> None:
            super().__init__(in_dim, out_dim)
            self.out = torch.nn.Linear(in_dim, 4 * out_dim)

    monkeypatch.setitem(MIXERS._entries, "wide", NeedsWidth)
    monkeypatch.setitem(MIXERS._origin, "wide", "a test")
    part.cache_clear()
    try:
        cfg = _cfg(tmp_path)
        cfg.mixer = {"name": "wide", "hidden": 4}  # a config file for it, conf/mixer/wide.yaml, without width
        with pytest.raises(SchemaError) as err:
            train(cfg, tmp_path / "run")
        assert (err.value.kind, err.value.key) == ("missing", "mixer.width")
    finally:
        part.cache_clear()
