"""User errors and bugs look different: a ``CicfwError`` (what a user can fix) is one ``cicfw: error:`` line
and exit status 2; any other exception is a bug and keeps its traceback; ``CICFW_DEBUG=1`` shows the
traceback of a user error too."""
from __future__ import annotations

import os
import pickle
import subprocess
import sys

import pytest

from cicfw.core import errors
from cicfw.core.errors import CicfwError, ConfigError, report_user_errors


def _raise(err: BaseException):
    return lambda: (_ for _ in ()).throw(err)


def test_a_config_error_names_the_key_the_value_and_what_is_accepted():
    err = ConfigError("model.lr", -1, "a number > 0")
    assert isinstance(err, CicfwError) and isinstance(err, ValueError)
    assert (err.key, err.value, err.accepted) == ("model.lr", -1, "a number > 0")
    assert "model.lr" in str(err) and "-1" in str(err) and "a number > 0" in str(err)
    again = pickle.loads(pickle.dumps(err))  # a multirun launcher may carry it to another process
    assert (type(again), again.key, again.value, str(again)) == (ConfigError, "model.lr", -1, str(err))


def test_the_user_errors_are_one_family():
    from cicfw.benchmark.app import OutputWriteError
    from cicfw.benchmark.journal import RunFolderError as JournalFolderError
    from cicfw.carla_client.backend import CarlaError, CarlaNotInstalled
    from cicfw.collect.errors import CollectError
    from cicfw.core.config_checks import SchemaError
    from cicfw.core.locks import FolderBusy
    from cicfw.core.run_folder import RunFolderError
    from cicfw.data.cil_hdf5 import CILFormatError
    from cicfw.data.images import DataChangedError
    from cicfw.diagnose.steer_diagnostic import DiagnosticError
    from cicfw.export.agent import AgentInputError
    from cicfw.export.app import ExportError
    from cicfw.model.checkpoint import CheckpointError
    from cicfw.registry import MIXERS, UnknownNameError
    from cicfw.reproduction.app import ReproduceError
    from cicfw.sim.town.model import TownError
    from cicfw.train.app import CheckpointWriteError

    for kind in (OutputWriteError, JournalFolderError, CarlaError, CarlaNotInstalled, CollectError, SchemaError,
                 FolderBusy, RunFolderError, CILFormatError, DataChangedError, DiagnosticError, AgentInputError,
                 ExportError, CheckpointError, UnknownNameError, ReproduceError, TownError, CheckpointWriteError):
        assert issubclass(kind, CicfwError), kind
    with pytest.raises(UnknownNameError) as err:
        MIXERS.get("nosuch")
    assert isinstance(err.value, KeyError) and err.value.value == "nosuch"


def test_a_user_error_is_one_line_and_status_2(capsys, monkeypatch):
    monkeypatch.delenv("CICFW_DEBUG", raising=False)
    with pytest.raises(SystemExit) as exit_:
        report_user_errors(_raise(ConfigError("seed", "abc", "an integer")))()
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("cicfw: error: seed") and "'abc'" in err and err.count("\n") == 1


@pytest.mark.parametrize("bug", [ValueError("operands could not be broadcast together"), TypeError("x"),
                                 KeyError("k")])
def test_any_other_exception_keeps_its_traceback(bug, capsys):
    with pytest.raises(type(bug)):
        report_user_errors(_raise(bug))()
    assert "cicfw: error" not in capsys.readouterr().err


def test_cicfw_debug_shows_the_traceback_of_a_user_error(capsys, monkeypatch):
    monkeypatch.setenv("CICFW_DEBUG", "1")
    with pytest.raises(SystemExit) as exit_:
        report_user_errors(_raise(ConfigError("seed", "abc", "an integer")))()
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" in err and "ConfigError" in err and "cicfw: error: seed" in err


# ---- the apps, end to end -----------------------------------------------------------------------------

def _argv(tmp_path, *args):
    from cicfw.testing import write_tiny_dataset

    data = write_tiny_dataset(tmp_path / "data", n_files=4, n=16)
    return ["data=cil_hdf5", f"data.path={data}", "data.batch_size=8", "data.val_batch_size=8",
            "progress_bar=false", "trainer.fast_dev_run=true", f"hydra.run.dir={tmp_path}/run", *args]


def _train(tmp_path, *args, env=None):
    """``python -m cicfw.train`` in this interpreter (``run_app_in_process``): what it prints and exits with."""
    from conftest import run_app_in_process

    env = {"CICFW_DEBUG": None, "HYDRA_FULL_ERROR": None} | (env or {})
    return run_app_in_process("cicfw.train", *_argv(tmp_path, *args), env=env)


@pytest.mark.slow
def test_a_planted_bug_in_a_mixer_prints_its_traceback(tmp_path, monkeypatch):
    """A bug planted in a mixer: its forward raises a ValueError, as a numpy broadcast or a shape mismatch would."""
    from cicfw.model.mixers.independent import IndependentMixer

    def forward(self, h):
        raise ValueError("operands could not be broadcast together with shapes (8,4) (3,)")

    monkeypatch.setattr(IndependentMixer, "forward", forward)
    run = _train(tmp_path)
    assert run.returncode not in (0, 2), run.stderr[-2000:]
    assert "Traceback" in run.stderr and "ValueError: operands could not be broadcast" in run.stderr
    assert "cicfw: error" not in run.stderr


@pytest.mark.slow
def test_a_wrong_key_is_one_line(tmp_path):
    """Through the real ``python -m`` entry (its own handlers, its own stderr): refused while composing."""
    env = {k: v for k, v in os.environ.items() if k not in ("CICFW_DEBUG", "HYDRA_FULL_ERROR")}
    run = subprocess.run([sys.executable, "-m", "cicfw.train", *_argv(tmp_path, "mixer.hiden=64")],
                         capture_output=True, text=True, timeout=300, env=env)
    assert run.returncode == 2
    lines = [ln for ln in run.stderr.splitlines() if ln.startswith("cicfw:")]
    assert len(lines) == 1 and "mixer.hiden" in lines[0], run.stderr[-2000:]
    assert "Traceback" not in run.stderr


@pytest.mark.slow
def test_cicfw_debug_shows_a_user_error_s_traceback_in_an_app(tmp_path):
    quiet = _train(tmp_path, "data.batch_size=6")  # the data module refuses it: a constructor's check
    assert quiet.returncode == 2 and "Traceback" not in quiet.stderr, quiet.stderr[-2000:]
    assert "cicfw: error: data.batch_size" in quiet.stderr
    loud = _train(tmp_path, "data.batch_size=6", env={"CICFW_DEBUG": "1"})
    assert loud.returncode == 2 and "Traceback" in loud.stderr and "cicfw: error: data.batch_size" in loud.stderr
