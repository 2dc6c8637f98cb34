"""SIGTERM (a cluster scheduler, ``timeout``, ``kill``) is a stop, not a crash: every app wrapped by
``report_user_errors`` says what it kept in one line, exits 143, and cleans up as after Ctrl-C; collect's
workers leave nothing behind, not even a resource-tracker warning."""
from __future__ import annotations

import json
import multiprocessing.resource_tracker as resource_tracker
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cicfw.collect import LOCK_NAME, collect_dataset
from cicfw.core.errors import CicfwError, report_user_errors
from conftest import process_alive

TINY = {"episodes": 2, "seconds": 2, "weathers": ["ClearNoon"], "cameras": ["centre"]}

STOPPED = """
import os, signal, sys, time
from cicfw.core.errors import on_interrupt, report_user_errors

@report_user_errors
def main():
    with on_interrupt("kept: nothing"):
        if sys.argv[1] == "fork":
            child = os.fork()
            if child == 0:  # a forked worker inherits the handler: it must die of SIGTERM, not raise
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(30)
                os._exit(0)
            _, status = os.waitpid(child, 0)
            print("child", os.WTERMSIG(status) if os.WIFSIGNALED(status) else "exited", flush=True)
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(30)

main()
"""


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", STOPPED, *args], capture_output=True, text=True, timeout=120)


def test_sigterm_is_one_line_and_status_143():
    proc = _run("plain")
    assert proc.returncode == 143, proc.stderr
    assert proc.stderr.splitlines() == ["cicfw: interrupted (SIGTERM); kept: nothing"]


def test_a_forked_child_still_dies_of_sigterm():
    proc = _run("fork")
    assert proc.stdout.split() == ["child", str(int(signal.SIGTERM))], proc.stderr
    assert proc.returncode == 143


def test_the_previous_sigterm_handler_is_back_afterwards():
    def mine(signum, frame):
        pass

    old = signal.signal(signal.SIGTERM, mine)
    try:
        assert report_user_errors(lambda: 3)() == 3
        assert signal.getsignal(signal.SIGTERM) is mine
        with pytest.raises(SystemExit):
            report_user_errors(lambda: (_ for _ in ()).throw(CicfwError("x")))()
        assert signal.getsignal(signal.SIGTERM) is mine
    finally:
        signal.signal(signal.SIGTERM, old)


# ------------------------------------------------------------------------------------------------ collect


def _holder(out: Path) -> dict:
    try:
        return json.loads((out / LOCK_NAME).read_text() or "{}")
    except (OSError, ValueError):
        return {}




def _wait_for(pred, proc: subprocess.Popen, what: str, timeout: float = 600) -> None:
    t0 = time.monotonic()
    while not pred():
        if proc.poll() is not None:
            pytest.fail(f"collect exited ({proc.returncode}) before {what}: {proc.stderr.read()}")
        if time.monotonic() - t0 > timeout:
            pytest.fail(f"timed out waiting for {what}")
        time.sleep(0.1)


@pytest.mark.slow  # collects a dataset
def test_sigterm_to_collect_ends_its_workers_and_leaves_no_part_file(tmp_path: Path):
    out = tmp_path / "ds"
    p = subprocess.Popen([sys.executable, "-m", "cicfw.collect", f"out_dir={out}", "episodes=6", "seconds=4",
                          "weathers=[ClearNoon]", "cameras=[centre]", "workers=2"],
                         cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        _wait_for(lambda: len(_holder(out).get("workers", [])) == 2, p, "two workers")
        workers = _holder(out)["workers"]
        half = out / f".ep0000_town_a_ClearNoon_000.h5.{workers[0]}-0a1b2c3d.part"  # as a killed write leaves it
        half.write_bytes(b"\0" * 1024)
        p.send_signal(signal.SIGTERM)
        _, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert p.returncode == 143, err
    assert "Traceback" not in err and "resource_tracker" not in err, err
    assert err.strip().splitlines()[-1] == (f"cicfw: interrupted (SIGTERM); finished episodes are kept in {out}: "
                                            f"rerun the same command to resume")
    assert not any(process_alive(w) for w in workers)
    assert not [q.name for q in out.rglob(".*") if q.is_file() and q.name != LOCK_NAME]
    assert _holder(out) == {}


@pytest.mark.slow  # collects a dataset
def test_collect_workers_hold_nothing_the_resource_tracker_must_clean(tmp_path: Path, monkeypatch):
    """Named semaphores (a spawn Queue's) are left to finalizers; the tracker warned of them after the
    app's last line. The workers' pipes register nothing."""
    registered = []
    real = resource_tracker.register
    monkeypatch.setattr(resource_tracker, "register", lambda name, rtype: (registered.append(rtype), real(name, rtype)))
    # the benchmark tests' small town: each worker bakes its ground in half town_a's CPU time
    small = str(Path(__file__).parent / "data" / "bench_town.yaml")
    meta = json.loads(collect_dataset({**TINY, "workers": 2, "towns": [small]}, tmp_path / "ds",
                                      progress=False).read_text())
    assert meta["complete"] and meta["counts"]["episodes"] == 2
    assert registered == []
