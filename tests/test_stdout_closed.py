"""A closed or full stdout: a closed pipe (``app | head``) loses and mis-marks nothing, the app exits quietly
with its results; a stdout that cannot be written (a full disk) is one line at exit, never a traceback."""
from __future__ import annotations

import errno
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from cicfw.core import errors

#: two rows of a published folder, for an entry module run by itself (not through the ``cicfw`` script)
ROWS = [str(Path(__file__).resolve().parents[1] / "docs" / "results" / "converged" / "cells" / r) for r in ("cil", "gtu")]


class _Failing:
    """A stream whose writes fail with ``code`` from the ``after``-th write on."""

    def __init__(self, code: int, after: int = 0) -> None:
        self.code, self.after, self.written = code, after, []

    def write(self, text: str) -> int:
        if len(self.written) >= self.after:
            raise OSError(self.code, os.strerror(self.code))
        self.written.append(text)
        return len(text)

    def flush(self) -> None:
        pass

    def fileno(self) -> int:
        raise OSError(errno.EBADF, "no descriptor")  # the guard's redirect to the null device is skipped


@pytest.mark.parametrize("code, closed, failure", [(errno.EPIPE, True, None), (errno.ENOSPC, False, errno.ENOSPC)])
def test_a_failed_write_to_stdout_is_noted_and_ends_nothing(code, closed, failure):
    out = errors.GuardedStdout(_Failing(code, after=1))
    assert out.write("first\n") == 6
    assert out.write("second\n") == 7  # no exception: the app goes on with its work
    out.write("third\n")
    out.flush()
    assert out._stream.written == ["first\n"]
    assert out.closed_pipe is closed
    assert (out.failure.errno if out.failure else None) == failure


def _env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if k not in ("CICFW_DEBUG", "HYDRA_FULL_ERROR")}


@pytest.mark.slow
@pytest.mark.parametrize("args, unbuffered", [(["cicfw.cli", "plugins"], "1"), (["cicfw.cli", "plugins"], ""),
                                              (["cicfw.train", "--help"], ""), (["cicfw.cli"], "1"),
                                              (["cicfw.reproduction.paired_switch", *ROWS], "")])
def test_a_full_stdout_is_one_line_and_a_failed_status(args, unbuffered):
    env = {**_env(), "PYTHONUNBUFFERED": unbuffered}
    with open("/dev/full", "w") as full:
        run = subprocess.run([sys.executable, "-m", *args], stdout=full, stderr=subprocess.PIPE, text=True,
                             timeout=300, env=env)
    assert run.returncode == 2, run.stderr[-2000:]
    assert "Traceback" not in run.stderr
    assert run.stderr.splitlines() == [f"cicfw: error: could not write to stdout: {os.strerror(errno.ENOSPC)}"]


@pytest.mark.slow
def test_an_evaluation_piped_into_head_finishes_complete(tmp_path):
    """Its reader gone after one line, the evaluation drives every episode, writes its report as complete
    and exits 0 without a word; its log file says where stdout stopped."""
    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "cicfw.evaluate", "policy=expert", "suite.limit=1",
                             "runner.workers=1", "maps=false", "sim.route_before=6",
                             "sim.max_deviation=2", f"hydra.run.dir={out}"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env={**_env(), "CICFW_CACHE": str(tmp_path / "c")})
    assert proc.stdout.readline()
    proc.stdout.close()  # as `| head -1` does
    stderr = proc.stderr.read()
    assert proc.wait(timeout=300) == 0, stderr[-2000:]
    assert stderr == ""
    summary = json.loads((out / "summary.json").read_text())
    assert summary["complete"] is True and summary["episodes"] == 8
    assert "stdout was closed" in (out / "evaluate.log").read_text()


@pytest.mark.slow
def test_a_full_stdout_after_a_traceback_keeps_status_1():
    """A bug's traceback, with a stdout that could not be written too: the line about stdout is added, the
    status stays Python's 1 for a traceback, not 2 (a user error's)."""
    status = 1
    script = ("from cicfw.core.errors import install_app_handlers\ninstall_app_handlers()\nprint('x' * 100000)\n"
              "raise RuntimeError('a bug')\n")
    with open("/dev/full", "w") as full:
        run = subprocess.run([sys.executable, "-c", script], stdout=full, stderr=subprocess.PIPE, text=True,
                             timeout=120, env=_env())
    assert run.returncode == status, run.stderr[-2000:]
    assert "RuntimeError: a bug" in run.stderr
    assert run.stderr.splitlines()[-1] == f"cicfw: error: could not write to stdout: {os.strerror(errno.ENOSPC)}"
