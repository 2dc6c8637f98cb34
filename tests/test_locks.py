"""The project's folder lock (``cicfw.core.locks.FolderLock``) and its users: the collection, the evaluation's run
folder, the reproduction's results folder and the sweep summary. A holder is named in a refusal, a dead
holder's record is taken over with a warning, a waiter waits as long as it is told, and no lock file is
left behind when a run ends."""
from __future__ import annotations

import json
import logging
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from cicfw.benchmark.journal import LOCK_NAME as EVALUATE_LOCK
from cicfw.benchmark.journal import EpisodeLog, RunFolderError
from cicfw.collect import LOCK_NAME as COLLECT_LOCK
from cicfw.collect import FolderLock as CollectLock
from cicfw.collect import FolderLockedError
from cicfw.core.errors import CicfwError
from cicfw.core.locks import FolderBusy, FolderLock
from cicfw.reproduction.lock import LOCK_FILE, ResultsLock
from cicfw.reproduction.report import check_no_live_reproduction
from cicfw.core.sweeps import ROWS_DIR, RowsLock, rebuild_summary

HOLDER = """
import sys, time
from cicfw.core.locks import FolderLock
FolderLock(sys.argv[1], info={"what": "the holder"}).acquire()
print("held", flush=True)
time.sleep(120)
"""


@pytest.fixture
def holder(tmp_path: Path):
    """Another process holding ``tmp_path/run``'s lock."""
    p = subprocess.Popen([sys.executable, "-c", HOLDER, str(tmp_path / "run")], stdout=subprocess.PIPE, text=True)
    try:
        assert p.stdout.readline().strip() == "held"
        yield p
    finally:
        p.kill()
        p.wait()


def dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def leave_record(folder: Path, name: str, **record) -> Path:
    """A lock file as a killed holder leaves it: its record, no flock."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / name).write_text(json.dumps(record))
    return folder / name


def test_another_process_is_refused_in_one_line_naming_the_holder(holder, tmp_path: Path):
    with pytest.raises(FolderBusy) as err:
        FolderLock(tmp_path / "run").acquire()
    msg = str(err.value)
    assert err.value.value == tmp_path / "run" and str(tmp_path / "run") in msg and "\n" not in msg
    assert f"pid {holder.pid}" in msg and socket.gethostname() in msg and "the holder" in msg  # who holds it
    record = json.loads((tmp_path / "run" / ".lock").read_text())
    assert record["pid"] == holder.pid and "command" in record and record["what"] == "the holder"


def test_the_lock_file_and_a_folder_the_lock_made_go_when_it_ends(tmp_path: Path):
    with FolderLock(tmp_path / "new") as lock:
        assert json.loads(lock.path.read_text())["pid"] == os.getpid()
    assert not (tmp_path / "new").exists()
    (tmp_path / "kept").mkdir()
    with FolderLock(tmp_path / "kept"):
        (tmp_path / "kept" / "result.txt").write_text("x")
    assert [p.name for p in (tmp_path / "kept").iterdir()] == ["result.txt"]


def test_a_waiter_waits_as_long_as_it_is_told(tmp_path: Path, caplog):
    first = FolderLock(tmp_path).acquire()
    t0 = time.monotonic()
    with pytest.raises(FolderBusy):
        FolderLock(tmp_path, wait=0.6).acquire()
    assert time.monotonic() - t0 >= 0.6
    threading.Timer(0.8, first.release).start()
    t0 = time.monotonic()
    with caplog.at_level(logging.WARNING, logger="cicfw.core.locks"), FolderLock(tmp_path, wait=30):
        assert time.monotonic() - t0 >= 0.7
    assert f"waiting for {tmp_path}: another process holds it (pid {os.getpid()}" in caplog.text
    assert not (tmp_path / ".lock").exists()


def test_a_waiter_on_a_file_its_holder_removed_takes_the_new_one(tmp_path: Path):
    """A holder finishing unlinks the file a waiter may have opened already: the waiter must lock the
    file at the path, or two processes would hold two files at one path."""
    class Late(FolderLock):
        def _open(self) -> int:
            fd = super()._open()
            if not hasattr(self, "seen"):
                self.seen = True
                self.path.unlink()  # the holder finished between this open and the flock
            return fd

    with Late(tmp_path) as lock:
        assert lock.path.is_file() and os.fstat(lock.fd).st_ino == lock.path.stat().st_ino
        with pytest.raises(FolderBusy):
            FolderLock(tmp_path).acquire()


def test_a_dead_holders_record_is_taken_over_with_a_warning(tmp_path: Path, caplog):
    pid = dead_pid()
    path = leave_record(tmp_path, ".lock", pid=pid, host="elsewhere", started="2020-01-01 00:00:00")
    with caplog.at_level(logging.WARNING, logger="cicfw.core.locks"), FolderLock(tmp_path) as lock:
        assert json.loads(path.read_text())["pid"] == os.getpid() and lock.fd is not None
    assert (f"{tmp_path}: taking over the stale lock of pid {pid} on elsewhere (started 2020-01-01 00:00:00), "
            f"which is no longer running") in caplog.text
    assert not path.exists()


def test_with_check_pid_only_a_gone_pid_on_this_host_is_taken_over(tmp_path: Path, caplog):
    class Careful(FolderLock):
        check_pid = True

    host = socket.gethostname()
    path = leave_record(tmp_path, ".lock", pid=1, host="elsewhere", started="2020-01-01 00:00:00")
    with pytest.raises(FolderBusy) as err:
        Careful(tmp_path).acquire()
    assert "pid 1" in str(err.value) and "elsewhere" in str(err.value) and str(path) in str(err.value)  # to delete
    leave_record(tmp_path, ".lock", pid=os.getppid(), host=host, started="x", started_epoch=time.time())
    with pytest.raises(FolderBusy) as err:
        Careful(tmp_path).acquire()  # alive here, though its flock is free: not taken
    assert f"pid {os.getppid()}" in str(err.value) and host in str(err.value)
    assert path.is_file()
    leave_record(tmp_path, ".lock", pid=dead_pid(), host=host, started="2020-01-01 00:00:00")
    with caplog.at_level(logging.WARNING, logger="cicfw.core.locks"), Careful(tmp_path):
        pass
    assert "taking over the stale lock" in caplog.text and not path.exists()


def test_update_keeps_the_start_and_adds_keys(tmp_path: Path):
    with FolderLock(tmp_path, info={"what": "a test"}) as lock:
        before = json.loads(lock.path.read_text())
        lock.update(workers=[1, 2])
        after = json.loads(lock.path.read_text())
    assert after == {**before, "workers": [1, 2]}


# ---- the users: each its own words, the same lock ------------------------------------------------
def test_the_collection_lock_names_its_holder_and_takes_over_a_killed_collector(tmp_path: Path, caplog):
    with CollectLock(tmp_path, 0, {"what": "a test"}):
        with pytest.raises(FolderLockedError) as err:
            CollectLock(tmp_path, 0).acquire()
        assert (err.value.key, err.value.value) == ("out_dir", tmp_path)
        assert f"pid {os.getpid()}" in str(err.value) and "a test" in str(err.value)
    assert not (tmp_path / COLLECT_LOCK).exists()
    pid = dead_pid()
    leave_record(tmp_path, COLLECT_LOCK, pid=pid, host=socket.gethostname(), started="2020-01-01 00:00:00")
    with caplog.at_level(logging.WARNING, logger="cicfw.collect"), CollectLock(tmp_path, 0):
        pass
    assert f"taking over the stale lock of pid {pid}" in caplog.text


def test_an_evaluation_folder_is_refused_to_a_second_writer_and_left_without_a_lock(tmp_path: Path, caplog):
    fp = {"policy": {"name": "expert"}}
    with EpisodeLog.open(tmp_path / "run", fp):
        assert (tmp_path / "run" / EVALUATE_LOCK).is_file()
        with pytest.raises(RunFolderError) as err:
            EpisodeLog.open(tmp_path / "run", fp)
        assert err.value.value == tmp_path / "run" and f"pid {os.getpid()}" in str(err.value)
    assert not (tmp_path / "run" / EVALUATE_LOCK).exists()
    pid = dead_pid()
    leave_record(tmp_path / "run", EVALUATE_LOCK, pid=pid, host=socket.gethostname(), started="2020-01-01 00:00:00")
    with caplog.at_level(logging.WARNING, logger="cicfw.core.locks"):
        EpisodeLog.open(tmp_path / "run", fp).close()
    assert f"taking over the stale lock of pid {pid}" in caplog.text
    assert not (tmp_path / "run" / EVALUATE_LOCK).exists()


def test_the_results_lock_refuses_a_live_holder_and_leaves_no_file(tmp_path: Path):
    out = tmp_path / "results"
    with ResultsLock(out):
        with pytest.raises(FolderBusy) as err:
            ResultsLock(out).acquire()
        assert (err.value.key, err.value.value) == ("results_dir", out) and f"pid {os.getpid()}" in str(err.value)
    assert not out.exists()  # made by the lock, nothing written into it
    path = leave_record(out, LOCK_FILE, pid=1, host="elsewhere", started="2020-01-01 00:00:00")
    with pytest.raises(FolderBusy) as err:
        ResultsLock(out).acquire()
    assert str(path) in str(err.value)  # the stale record to delete
    assert path.is_file()


def test_the_results_lock_names_the_command_that_holds_it(tmp_path: Path):
    """A `cicfw report` holding a results folder is named by its record's command, not called a reproduce run;
    a record without a command is "another process". The report's own check of a live holder says the same."""
    out = tmp_path / "results"
    with ResultsLock(out) as held:
        held.update(command="report.py R1")
        with pytest.raises(FolderBusy) as err:
            ResultsLock(out).acquire()
        assert err.value.key == "results_dir" and "`report.py R1`" in str(err.value), str(err.value)
        assert "reproduce run" not in str(err.value)
        with pytest.raises(CicfwError) as err:
            check_no_live_reproduction(out)
        assert err.value.key == "results_dir" and "`report.py R1`" in str(err.value), str(err.value)
        assert "running reproduce" not in str(err.value)
    path = leave_record(out, LOCK_FILE, pid=1, host="elsewhere", started="2020-01-01 00:00:00")
    with pytest.raises(FolderBusy) as err:
        ResultsLock(out).acquire()
    assert "another process (pid 1" in str(err.value) and str(path) in str(err.value), str(err.value)


def test_the_sweep_summary_waits_for_its_rows_and_leaves_no_lock(tmp_path: Path):
    rows = tmp_path / ROWS_DIR
    rows.mkdir()
    held = RowsLock(rows, wait=None).acquire()
    threading.Timer(0.5, held.release).start()
    t0 = time.monotonic()
    target = rebuild_summary(tmp_path)
    assert time.monotonic() - t0 >= 0.4 and target.is_file()
    assert list(rows.iterdir()) == []
