"""SIGTERM (``timeout``, a scheduler, ``kill``) and Ctrl-C while an app is still importing its modules or
composing its config: one line (``cicfw: interrupted (SIGTERM)``), status 143 (130 for Ctrl-C), as a stop
later in the run says it, not a silent exit 143 (SIGTERM's default) or a KeyboardInterrupt traceback.
Each app's entry point (``__main__``, the entry module, the ``cicfw`` script) installs the handler before it
imports the app; importing a cicfw module changes nothing."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = [pytest.mark.slow,  # starts the apps (each is stopped while it imports)
              pytest.mark.skipif(not Path("/proc/self/status").is_file(), reason="reads /proc/<pid>/status")]

ROOT = Path(__file__).resolve().parents[1]


def _catches_sigterm(pid: int) -> bool:
    """Whether process ``pid`` has a handler for SIGTERM now (SigCgt in /proc/<pid>/status)."""
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    mask = next(int(line.split()[1], 16) for line in text.splitlines() if line.startswith("SigCgt:"))
    return bool(mask >> (signal.SIGTERM - 1) & 1)


def _stopped_while_importing(args: list[str], sig: int, tmp_path: Path) -> subprocess.CompletedProcess:
    """Start ``args``; send ``sig`` as soon as the process catches SIGTERM (its entry point has installed the
    handler: the app's own imports, Hydra's among them, and its config composition still to come)."""
    proc = subprocess.Popen(args, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        t0 = time.monotonic()
        while not _catches_sigterm(proc.pid):
            if proc.poll() is not None or time.monotonic() - t0 > 120:
                pytest.fail(f"{args} never caught SIGTERM (exit {proc.poll()}): {proc.communicate()[1][-2000:]}")
            time.sleep(0.001)
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return subprocess.CompletedProcess(args, proc.returncode, out, err)


APPS = [
    ["-m", "cicfw.evaluate", "policy=expert"],
    ["-m", "cicfw.train", "debug=fast"],
    ["-m", "cicfw.collect", "episodes=1"],
    ["-m", "cicfw.reproduce", "budget=smoke"],
    ["-m", "cicfw.cli", "export"],
]


@pytest.mark.parametrize("app", APPS, ids=lambda a: a[1])
def test_sigterm_while_an_app_imports_is_one_line_and_143(app, tmp_path):
    proc = _stopped_while_importing([sys.executable, *app, f"hydra.run.dir={tmp_path / 'run'}"], signal.SIGTERM,
                                    tmp_path)
    assert proc.returncode == 143, proc.stderr[-3000:]
    assert proc.stderr.strip().splitlines() == ["cicfw: interrupted (SIGTERM)"], proc.stderr[-3000:]
    assert not (tmp_path / "run").exists()  # stopped before the app began: no run folder


def test_ctrl_c_while_an_app_imports_is_one_line_and_130(tmp_path):
    proc = _stopped_while_importing([sys.executable, "-m", "cicfw.evaluate", "policy=expert",
                                     f"hydra.run.dir={tmp_path / 'run'}"], signal.SIGINT, tmp_path)
    assert proc.returncode == 130, proc.stderr[-3000:]
    assert proc.stderr.strip().splitlines() == ["cicfw: interrupted"], proc.stderr[-3000:]
    assert not (tmp_path / "run").exists()


def test_the_console_script_catches_sigterm_first_thing(tmp_path):
    script = Path(sys.executable).parent / "cicfw"
    if not script.is_file():
        pytest.skip("no cicfw console script beside this Python")
    proc = _stopped_while_importing([str(script), "evaluate", "policy=expert", f"hydra.run.dir={tmp_path / 'run'}"],
                                    signal.SIGTERM, tmp_path)
    assert proc.returncode == 143 and proc.stderr.strip().splitlines() == ["cicfw: interrupted (SIGTERM)"], proc.stderr
    assert not (tmp_path / "run").exists()


def test_importing_cicfw_changes_nothing_in_the_process():
    """Not even in a process started as an app would be (``python -m cicfw.train``: ``sys.argv[0]`` is ``-m``
    while the package imports), nor with an empty CICFW_CACHE, which the apps' entry points drop. The
    libraries cicfw builds on are imported first: torch, Lightning and OpenCV set variables of their own."""
    code = ("import os, signal, sys; sys.argv = ['-m']; sys.orig_argv = [sys.executable, '-m', 'cicfw.train']; "
            "import cv2, hydra, lightning, torch, torch._inductor.config; "
            "before = (dict(os.environ), signal.getsignal(signal.SIGTERM), sys.excepthook); "
            "import cicfw, cicfw.conf, cicfw.train.app, cicfw.benchmark.app; "
            "assert before == (dict(os.environ), signal.getsignal(signal.SIGTERM), sys.excepthook); print('same')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                         env={**os.environ, "CICFW_CACHE": ""})
    assert out.returncode == 0 and out.stdout.split() == ["same"], out.stderr[-3000:]


def test_other_errors_keep_their_traceback(tmp_path):
    """The hook speaks for interrupts only: an app's crash during its imports still shows where."""
    code = ("import runpy, sys; sys.argv = ['-m']; sys.orig_argv = [sys.executable, '-m', 'cicfw.nosuch']; "
            "import cicfw; raise RuntimeError('boom')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert out.returncode == 1 and "Traceback" in out.stderr and "RuntimeError: boom" in out.stderr, out.stderr


def test_the_one_line_hook_is_in_place_before_sigterm_is_caught(monkeypatch):
    """A SIGTERM that arrives the moment the handler is installed (what the tests above send, as soon as the
    process catches it) must find the excepthook that prints its one line: the hook goes in first."""
    from cicfw.core import errors

    hook_when_caught = []

    def spy(sig, handler):  # records instead of installing: this test process keeps its own handlers
        if sig == signal.SIGTERM:
            hook_when_caught.append(sys.excepthook)

    before = sys.excepthook
    monkeypatch.setattr(sys, "excepthook", before)  # put back after the test
    monkeypatch.setattr(errors, "_installed", False)
    monkeypatch.setattr(errors.signal, "signal", spy)
    errors.install_app_handlers()
    assert len(hook_when_caught) == 1 and hook_when_caught[0] is not before


def test_a_relative_cicfw_cache_is_where_the_app_started(tmp_path):
    """hydra.job.chdir=true moves the app into its run folder before the config's ${oc.env:CICFW_CACHE} is read:
    a relative cache would be a new one inside every run folder, its dataset collected again there."""
    from conftest import run_app_in_process

    out = run_app_in_process("cicfw.collect", "episodes=1", "seconds=0.1", "workers=1", "cameras=[centre]",
                             "hydra.job.chdir=true", f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path,
                             env={"CICFW_CACHE": "cache"})
    assert out.returncode == 0, out.stderr[-3000:]
    assert (tmp_path / "cache" / "datasets" / "collected" / "dataset_metadata.json").is_file()
    assert not (tmp_path / "run" / "cache").exists()


def test_an_app_without_home_resolves_the_default_cache(monkeypatch):
    """A batch job's environment may lack HOME: the configs' default cache (${oc.env:HOME}/.cache/cicfw) is then
    the password database's home, as ``~`` is, not an interpolation traceback."""
    import pwd

    from cicfw.core import errors
    from conftest import compose_train

    monkeypatch.delenv("HOME", raising=False)  # put back after the test, with what install_app_handlers sets
    monkeypatch.delenv("CICFW_CACHE", raising=False)
    monkeypatch.setattr(errors, "_installed", True)  # the environment only: this process keeps its handlers
    errors.install_app_handlers()
    home = pwd.getpwuid(os.getuid()).pw_dir
    assert os.environ["HOME"] == home
    assert compose_train().data.path == f"{home}/.cache/cicfw/datasets/sim_default"
