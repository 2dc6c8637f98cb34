"""The collector never mixes or loses data: fault tests of the engine's guarantees.

Two collectors at once, a killed collector's workers, a full disk (a real 20 MB tmpfs where the machine
lets us mount one, and ENOSPC simulated everywhere), an unwritable folder, a town given by path, and
``complete`` meaning complete. Episodes are tiny (2 s, the centre camera) to keep this fast.
"""
from __future__ import annotations

import errno
import json
import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from omegaconf import OmegaConf

import cicfw.collect.dataset as dataset_mod
import cicfw.collect.writing as writing
import cicfw.core.files as files_mod
from cicfw.collect import (LOCK_NAME, CollectConfigError, CollectError, DiskFullError, FolderLock, FolderLockedError,
                              collect_dataset, episode_bytes, episode_plan, resolve_config)
from cicfw.data.cil_hdf5 import check_file, find_files
from conftest import process_alive

pytestmark = pytest.mark.slow  # trains, collects, drives or runs an app (pytest -m "not slow" skips it)

TINY = {"episodes": 2, "seconds": 2, "weathers": ["ClearNoon"], "cameras": ["centre"], "workers": 0}
#: the benchmark tests' small town: a process of its own bakes its ground in half town_a's CPU time
SMALL_TOWN = str(Path(__file__).parent / "data" / "bench_town.yaml")
COLLECTOR = ("import json, sys\nfrom cicfw.collect import collect_dataset\n"
             "collect_dataset(json.loads(sys.argv[1]), sys.argv[2], progress=False)\n")


def _meta(out: Path) -> dict:
    return json.loads((out / "dataset_metadata.json").read_text())


def _temp_files(out: Path) -> list[str]:
    """Every hidden file of the dataset but the lock file: what a write left half-done."""
    return sorted(str(p.relative_to(out)) for p in out.rglob(".*") if p.is_file() and p.name != LOCK_NAME)


def _holder(out: Path) -> dict:
    try:
        return json.loads((out / LOCK_NAME).read_text() or "{}")
    except (OSError, ValueError):
        return {}


def _wait_for(pred, timeout: float, what: str, proc: subprocess.Popen | None = None) -> None:
    t0 = time.monotonic()
    while not pred():
        if proc is not None and proc.poll() is not None:
            pytest.fail(f"the collector exited ({proc.returncode}) before {what}: {proc.stderr.read()}")
        if time.monotonic() - t0 > timeout:
            pytest.fail(f"timed out waiting for {what}")
        time.sleep(0.1)




def _collector(out: Path, cfg: dict) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", COLLECTOR, json.dumps(cfg), str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _mount_tmpfs(where: Path, options: str) -> None:
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(where)], capture_output=True, text=True)
    if r.returncode:
        pytest.skip(f"cannot mount a tmpfs here ({r.stderr.strip() or r.returncode})")


# ------------------------------------------------------------------------------------------------
# one writer per folder


def test_two_collectors_at_once_never_mix(tmp_path: Path, caplog):
    out = tmp_path / "ds"
    a_cfg = {**TINY, "episodes": 3, "seed": 0, "towns": [SMALL_TOWN]}  # only the first collector renders
    a = _collector(out, a_cfg)
    try:
        _wait_for(lambda: _holder(out).get("pid") == a.pid, 600, "the first collector to take the lock", a)
        # a second collector with another seed, told not to wait: one line naming the holder
        with pytest.raises(FolderLockedError) as err:
            collect_dataset({**a_cfg, "seed": 1, "lock_wait": 0}, out, progress=False)
        msg = str(err.value)
        assert err.value.key == "out_dir" and err.value.value == out.resolve()
        assert f"pid {a.pid}" in msg and socket.gethostname() in msg and "\n" not in msg
        # a third with the first one's config waits for it, then finds nothing left to do
        with caplog.at_level(logging.WARNING, logger="cicfw.collect"):
            meta = json.loads(collect_dataset({**a_cfg, "lock_wait": 300}, out, progress=False).read_text())
        assert f"waiting for {out}: another process is collecting into it (pid {a.pid}" in caplog.text
        assert a.wait(600) == 0, a.stderr.read()
    finally:
        if a.poll() is None:
            a.kill()
            a.wait()
    assert meta["complete"] and meta["seed"] == 0
    # the second one again, now that the folder is free: refused, it holds another config's dataset
    with pytest.raises(CollectConfigError) as err:
        collect_dataset({**a_cfg, "seed": 1, "lock_wait": 0}, out, progress=False)
    assert err.value.key == "out_dir" and err.value.value == out.resolve()
    # the folder holds exactly the first collector's plan: its episodes, seeds and files, nothing else
    plan = episode_plan(resolve_config(a_cfg))
    meta = _meta(out)
    assert {k: v["seed"] for k, v in meta["episodes"].items()} == {ep["id"]: ep["seed"] for ep in plan}
    assert sorted(meta["files"]) == [f.name for f in find_files(out)]
    assert all(check_file(f).n == meta["files"][f.name]["samples"] for f in find_files(out))
    markers = [json.loads(p.read_text()) for p in (out / ".episodes").glob("*.json")]
    assert {m["config_hash"] for m in markers} == {meta["config_hash"]} and len(markers) == 3
    assert _temp_files(out) == [] and _holder(out) == {}  # released: the holder record is cleared


def test_a_training_job_waits_for_the_one_filling_the_same_cache(tmp_path: Path, caplog):
    """train's ensure_data calls the collector with data.collect (lock_wait defaults to waiting), as two
    jobs of a multirun on data=sim_default do."""
    from cicfw.train.app import ensure_data

    out = tmp_path / "sim_default"
    out.mkdir()
    lock = FolderLock(out, 0, {"what": "the other job"}).acquire()
    threading.Timer(1.5, lock.release).start()
    collect = {k: v for k, v in TINY.items() if k != "workers"} | {"episodes": 1}
    t0 = time.monotonic()
    with caplog.at_level(logging.WARNING, logger="cicfw.collect"):
        ensure_data(OmegaConf.create({"path": str(out), "collect": collect}))
    assert time.monotonic() - t0 >= 1.4
    assert f"pid {os.getpid()} on {socket.gethostname()}" in caplog.text and "(the other job)" in caplog.text
    assert _meta(out)["complete"]


def test_the_lock_is_released_on_errors_and_names_its_holder(tmp_path: Path, monkeypatch):
    monkeypatch.setattr(dataset_mod, "run_episode", lambda *a, **k: (_ for _ in ()).throw(RuntimeError("boom")))
    with pytest.raises(RuntimeError, match="boom"):
        collect_dataset(TINY, tmp_path, progress=False)
    with FolderLock(tmp_path, 0, {"what": "a test"}):  # free again
        held = _holder(tmp_path)
        assert held["pid"] == os.getpid() and held["host"] == socket.gethostname() and held["what"] == "a test"
        with pytest.raises(FolderLockedError) as err:
            collect_dataset({**TINY, "lock_wait": 0}, tmp_path, progress=False)
        assert err.value.key == "out_dir" and err.value.value == tmp_path.resolve()
        assert f"pid {os.getpid()}" in str(err.value) and "a test" in str(err.value)  # the holder
        t0 = time.monotonic()
        with pytest.raises(FolderLockedError):
            collect_dataset({**TINY, "lock_wait": 0.6}, tmp_path, progress=False)
        assert time.monotonic() - t0 >= 0.6  # waited for it first
    # temporary names are unique to the process and to each call
    a, b = files_mod._temp_name(tmp_path / "x.h5", ".part"), files_mod._temp_name(tmp_path / "x.h5", ".part")
    assert a != b and a.name.startswith(f".x.h5.{os.getpid()}-") and a.suffix == ".part"


# ------------------------------------------------------------------------------------------------
# workers die with their parent


def test_workers_end_when_their_collector_is_killed(tmp_path: Path):
    out = tmp_path / "ds"
    cfg = {**TINY, "episodes": 6, "seconds": 4, "workers": 2}
    p = _collector(out, cfg)
    try:
        _wait_for(lambda: len(_holder(out).get("workers", [])) == 2, 600, "two workers", p)
        workers = _holder(out)["workers"]
        _wait_for(lambda: any((out / ".episodes").glob("*.json")), 600, "a first finished episode", p)
        assert all(process_alive(w) for w in workers)
        os.kill(p.pid, signal.SIGKILL)
        p.wait()
        t0 = time.monotonic()
        _wait_for(lambda: not any(process_alive(w) for w in workers), 10, "the workers to end after their parent")
        print(f"workers gone {time.monotonic() - t0:.2f} s after the collector was killed")
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    written = sorted(f.name for f in out.glob("*.h5"))
    time.sleep(1.5)
    assert sorted(f.name for f in out.glob("*.h5")) == written  # nothing is written after the kill
    assert not _meta(out)["complete"]
    # the lock died with the collector: a new one takes over at once and finishes the dataset
    meta = json.loads(collect_dataset({**cfg, "workers": 0, "lock_wait": 0}, out, progress=False).read_text())
    assert meta["complete"] and meta["counts"]["episodes"] == 6 and _temp_files(out) == []


PARENT = ("import os, subprocess, sys, time\n"
          "c = subprocess.Popen([sys.executable, '-c', sys.argv[1], str(os.getpid()), sys.argv[2]])\n"
          "print(c.pid, flush=True)\ntime.sleep(600)\n")
CHILD = """
import ctypes, sys, threading, time
mode = sys.argv[2]
if mode == "poll only":  # a platform without PR_SET_PDEATHSIG
    def no_prctl(*a, **k):
        raise OSError("no prctl here")
    ctypes.CDLL = no_prctl
if mode == "death signal only":  # no parent-pid poll
    class NoThread:
        def __init__(self, *a, **k):
            pass
        def start(self):
            pass
    threading.Thread = NoThread
from cicfw.collect import workers
if mode == "a collect worker":  # the real worker entry point, waiting for its next episode
    class Tasks:
        def get(self):
            print("ready", flush=True)
            time.sleep(600)
    workers._worker_main(0, {"name": "embedded"}, {}, "/nonexistent", int(sys.argv[1]), Tasks(), None)
else:
    workers._die_with_parent(int(sys.argv[1]))
    print("ready", flush=True)
    time.sleep(600)
"""


@pytest.mark.parametrize("mode", ["a collect worker", "death signal only", "poll only"])
def test_a_worker_process_dies_with_its_parent(mode: str):
    """The mechanisms one by one (the test above also passes through the workers' own parent check
    before they finalise a file): a collect worker, waiting for work, is gone soon after its parent is
    killed; so is a process with only the kernel's death signal (Linux), or only the parent-pid poll."""
    if mode == "death signal only" and not sys.platform.startswith("linux"):
        pytest.skip("PR_SET_PDEATHSIG is Linux's")
    parent = subprocess.Popen([sys.executable, "-c", PARENT, CHILD, mode], stdout=subprocess.PIPE, text=True)
    child = None
    try:
        child = int(parent.stdout.readline())
        assert parent.stdout.readline().strip() == "ready" and process_alive(child)
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait()
        _wait_for(lambda: not process_alive(child), 10, f"the child to die with its parent ({mode})")
    finally:
        if parent.poll() is None:
            parent.kill()
        if child is not None and process_alive(child):
            os.kill(child, signal.SIGKILL)


def test_ctrl_c_ends_the_workers_and_leaves_one_line(tmp_path: Path):
    out = tmp_path / "ds"
    p = subprocess.Popen([sys.executable, "-m", "cicfw.collect", f"out_dir={out}", "episodes=6", "seconds=4",
                          "weathers=[ClearNoon]", "cameras=[centre]", "workers=2"],
                         cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        _wait_for(lambda: len(_holder(out).get("workers", [])) == 2, 600, "two workers", p)
        workers = _holder(out)["workers"]
        time.sleep(1.0)
        p.send_signal(signal.SIGINT)
        _, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert p.returncode == 130 and "Traceback" not in err, err
    assert err.strip().splitlines()[-1] == (f"cicfw: interrupted; finished episodes are kept in {out}: rerun the "
                                            f"same command to resume")
    assert not any(process_alive(w) for w in workers) and _temp_files(out) == [] and _holder(out) == {}


def test_what_a_stopped_worker_left_is_removed_by_its_parent(tmp_path: Path, monkeypatch):
    def workers_that_die(cfg, todo, out_dir, n, on_marker, lock):
        fd, _ = files_mod.temp_beside(out_dir / "ep0000_town_a_ClearNoon_000.h5", ".part")
        os.write(fd, b"half a file")  # as if killed
        os.close(fd)
        raise CollectError("collect worker 1 (pid 1) died with exit code -9")

    monkeypatch.setattr(dataset_mod, "run_workers", workers_that_die)
    with pytest.raises(CollectError, match="died with exit code -9"):
        collect_dataset({**TINY, "workers": 2}, tmp_path, progress=False)
    assert _temp_files(tmp_path) == [] and not _meta(tmp_path)["complete"]


# ------------------------------------------------------------------------------------------------
# a full disk


@pytest.fixture
def small_disk(tmp_path: Path):
    """A real 20 MB tmpfs (root only; skipped with the reason where it cannot be mounted)."""
    d = tmp_path / "disk"
    d.mkdir()
    _mount_tmpfs(d, "size=20m")
    yield d
    subprocess.run(["umount", "-l", str(d)], capture_output=True)


def _fill(disk: Path, leave: int) -> Path:
    filler = disk / "filler.bin"
    with open(filler, "wb") as f:
        f.write(b"\0" * max(shutil.disk_usage(disk).free - leave, 0))
    return filler


def test_a_full_tmpfs_is_one_clear_error_and_leaves_no_temp_file(small_disk: Path, monkeypatch):
    out = small_disk / "ds"
    need = episode_bytes(resolve_config(TINY))
    filler = _fill(small_disk, int(1.5 * need))  # room for one episode, not two
    runs = []
    real_run = dataset_mod.run_episode
    monkeypatch.setattr(dataset_mod, "run_episode", lambda *a, **k: runs.append(1) or real_run(*a, **k))
    # the free-space check: refused before anything is simulated
    with pytest.raises(DiskFullError) as err:
        collect_dataset(TINY, out, progress=False)
    assert err.value.key == "out_dir" and err.value.value == out
    assert runs == [] and _temp_files(out) == []
    # with the check fooled, the second episode's write really hits ENOSPC: one clear error, no temp file,
    # no crash inside HDF5 (the file is built in memory and written with os.write)
    monkeypatch.setattr(writing, "_free_bytes", lambda path: 10**12)
    with pytest.raises(DiskFullError) as err:
        collect_dataset(TINY, out, progress=False)
    assert err.value.key == "out_dir" and err.value.value == out
    assert "ep0001_town_a_ClearNoon_000.h5" in str(err.value) and "\n" not in str(err.value)  # the file it wrote
    assert _temp_files(out) == [] and [f.name for f in find_files(out)] == ["ep0000_town_a_ClearNoon_000.h5"]
    assert not _meta(out)["complete"] and _meta(out)["counts"]["episodes"] == 1
    # space freed: the rerun finishes the dataset
    filler.unlink()
    assert json.loads(collect_dataset(TINY, out, progress=False).read_text())["complete"]


def test_enospc_in_the_middle_of_a_write_is_one_clear_error(tmp_path: Path, monkeypatch):
    """The same fault simulated (for machines where no tmpfs can be mounted): half a file, then ENOSPC."""
    real = files_mod.write_all

    def half_then_full(fd, data):
        if len(data) > 100_000:  # an HDF5 file, not a JSON one
            real(fd, memoryview(data)[: len(data) // 2])
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real(fd, data)

    monkeypatch.setattr(files_mod, "write_all", half_then_full)
    with pytest.raises(DiskFullError) as err:
        writing.write_files({tmp_path / "x.h5": b"\0" * 200_000})  # the write itself removes its temp file
    assert err.value.key == "out_dir" and err.value.value == tmp_path and "x.h5" in str(err.value)
    assert os.listdir(tmp_path) == []
    with pytest.raises(DiskFullError) as err:
        collect_dataset(TINY, tmp_path, progress=False)
    assert err.value.key == "out_dir" and err.value.value == tmp_path.resolve()
    assert "ep0000_town_a_ClearNoon_000.h5" in str(err.value) and "\n" not in str(err.value)
    assert _temp_files(tmp_path) == [] and not list(tmp_path.glob("*.h5")) and not _meta(tmp_path)["complete"]
    monkeypatch.setattr(files_mod, "write_all", real)
    assert json.loads(collect_dataset(TINY, tmp_path, progress=False).read_text())["complete"]


# ------------------------------------------------------------------------------------------------
# an unwritable folder, before anything is simulated


def test_a_file_in_place_of_the_folder_is_reported_before_simulating(tmp_path: Path, monkeypatch):
    monkeypatch.setattr(dataset_mod, "run_episode", lambda *a, **k: pytest.fail("simulated"))
    f = tmp_path / "a_file"
    f.write_text("x")
    for out in (f, f / "sub"):
        with pytest.raises(CollectError) as err:
            collect_dataset(TINY, out, progress=False)
        assert err.value.key == "out_dir" and err.value.value == out


def test_a_read_only_folder_is_reported_before_simulating(tmp_path: Path, monkeypatch):
    monkeypatch.setattr(dataset_mod, "run_episode", lambda *a, **k: pytest.fail("simulated"))
    ro = tmp_path / "ro"
    ro.mkdir()
    if os.geteuid() == 0:  # root ignores permission bits: a read-only file system it is
        _mount_tmpfs(ro, "ro,size=1m")
    else:
        ro.chmod(0o500)
    try:
        for out in (ro, ro / "sub"):
            with pytest.raises(CollectError) as err:
                collect_dataset(TINY, out, progress=False)
            assert err.value.key == "out_dir" and err.value.value == out
    finally:
        if os.geteuid() == 0:
            subprocess.run(["umount", "-l", str(ro)], capture_output=True)
        else:
            ro.chmod(0o700)


# ------------------------------------------------------------------------------------------------
# a town by path; complete means complete; no foreign files


def test_a_town_given_by_path(tmp_path: Path):
    from cicfw.sim.town import town_path

    town = tmp_path / "towns" / "my_town.yaml"
    town.parent.mkdir()
    shutil.copy(town_path("town_b"), town)
    cfg = {**TINY, "episodes": 1, "towns": [str(town)]}
    out = tmp_path / "ds"
    meta = json.loads(collect_dataset(cfg, out, progress=False).read_text())
    assert [f.name for f in find_files(out)] == ["ep0000_my_town_ClearNoon_000.h5"]
    assert meta["complete"] and meta["towns"] == [str(town.resolve())]
    assert meta["episodes"]["ep0000_my_town_ClearNoon"]["town"] == str(town.resolve())
    # the town file is part of the config: edited, it makes another dataset
    town.write_text(town.read_text() + "\n# edited\n")
    with pytest.raises(CollectConfigError) as err:
        collect_dataset(cfg, out, progress=False)
    assert err.value.key == "out_dir" and err.value.value == out.resolve()
    # two town files with one stem would share file names
    other = tmp_path / "b" / "my_town.yaml"
    other.parent.mkdir()
    shutil.copy(town, other)
    with pytest.raises(CollectConfigError) as err:
        resolve_config({**cfg, "towns": [str(town), str(other)]})
    assert err.value.key == "collect.towns" and err.value.value == "my_town"


def test_a_town_file_whose_name_is_too_long_for_the_episode_files_is_refused_before_simulating(tmp_path: Path,
                                                                                             monkeypatch):
    """A town file's stem goes into every episode's file names: one the filesystem cannot take is one line
    naming the town before anything is driven or written, not a write error after the episode."""
    from cicfw.sim.town import town_path

    monkeypatch.setattr(dataset_mod, "run_episode", lambda *a, **k: pytest.fail("simulated"))
    town = tmp_path / ("t" * 235 + ".yaml")  # a legal name (240 bytes), but not with the episode's prefix and suffix
    shutil.copy(town_path("town_b"), town)
    out = tmp_path / "ds"
    with pytest.raises(CollectConfigError) as err:
        collect_dataset({**TINY, "episodes": 1, "towns": [str(town)]}, out, progress=False)
    assert err.value.key == "collect.towns" and str(town) in str(err.value.value)
    assert not out.exists()


def test_a_town_file_name_too_long_only_in_a_worker_s_temporary_name_is_refused(tmp_path: Path, monkeypatch):
    """A worker writes the episode's parts under names holding its own pid, which may have more digits than the
    collector's: a town file's stem one byte too long for a 7-digit pid is refused before simulating."""
    from cicfw.core.run_folder import name_max
    from cicfw.sim.town import town_path

    monkeypatch.setattr(dataset_mod, "run_episode", lambda *a, **k: pytest.fail("simulated"))
    out = tmp_path / "ds"
    # .ep0000_<stem>_ClearNoon_000.h5.<7-digit pid>-<8 hex>.part: the stem plus 47 bytes
    town = tmp_path / ("t" * (name_max(tmp_path) + 1 - 47) + ".yaml")
    shutil.copy(town_path("town_b"), town)
    with pytest.raises(CollectConfigError) as err:
        collect_dataset({**TINY, "episodes": 1, "towns": [str(town)]}, out, progress=False)
    assert err.value.key == "collect.towns" and str(town) in str(err.value.value)
    assert not out.exists()


def test_complete_is_true_only_when_every_file_validates(tmp_path: Path, monkeypatch):
    assert json.loads(collect_dataset(TINY, tmp_path, progress=False).read_text())["complete"]
    first = tmp_path / "ep0000_town_a_ClearNoon_000.h5"
    original = first.read_bytes()
    real_run = dataset_mod.run_episode

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    for damage in ("truncate", "corrupt", "delete"):
        if damage == "truncate":
            first.write_bytes(original[: len(original) // 2])
        elif damage == "corrupt":  # same size, the HDF5 signature overwritten: only opening it tells
            first.write_bytes(b"\0" * 8 + original[8:])
        else:
            first.unlink()
        # a rerun that cannot redo the episode leaves the metadata saying incomplete
        monkeypatch.setattr(dataset_mod, "run_episode", interrupted)
        with pytest.raises(KeyboardInterrupt):
            collect_dataset(TINY, tmp_path, progress=False)
        meta = _meta(tmp_path)
        assert not meta["complete"] and meta["counts"]["episodes"] == 1, damage
        assert "ep0000_town_a_ClearNoon_000.h5" not in meta["files"] and not first.exists()  # never left to read
        # a rerun that can redoes exactly that episode, with the same bytes
        monkeypatch.setattr(dataset_mod, "run_episode", real_run)
        assert json.loads(collect_dataset(TINY, tmp_path, progress=False).read_text())["complete"]
        assert first.read_bytes() == original, damage


def test_a_folder_with_other_hdf5_files_is_refused(tmp_path: Path, monkeypatch):
    monkeypatch.setattr(dataset_mod, "run_episode", lambda *a, **k: pytest.fail("simulated"))
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "theirs.h5").write_bytes(b"not ours")
    with pytest.raises(CollectError) as err:
        collect_dataset(TINY, tmp_path, progress=False)
    assert err.value.key == "out_dir" and err.value.value == tmp_path.resolve()
    assert "sub/theirs.h5" in str(err.value)  # names a file it would not mix in


def test_hdf5_files_with_the_collection_s_names_but_no_record_of_it_are_refused(tmp_path: Path, monkeypatch):
    """A collection's files copied without its records (``dataset_metadata.json``, ``.episodes/``) are the
    user's: refused before anything is written, though their names are the planned episodes' own. Copied with
    the episodes' markers, they are the collection's: a rerun finds them done and collects nothing."""
    done = tmp_path / "done"
    collect_dataset(TINY, done, progress=False)
    names = sorted(p.name for p in done.glob("*.h5"))
    assert len(names) == 2
    monkeypatch.setattr(dataset_mod, "run_episode", lambda *a, **k: pytest.fail("simulated"))
    mine = tmp_path / "mine"
    mine.mkdir()
    shutil.copy(done / names[0], mine / names[1])  # another episode's bytes under a planned name
    (mine / "README.txt").write_text("notes")
    before = _listing(mine)
    with pytest.raises(CollectError) as err:
        collect_dataset(TINY, mine, progress=False)
    assert (err.value.key, err.value.value) == ("out_dir", mine.resolve())
    assert names[1] in str(err.value)
    assert _listing(mine) == before  # no lock file, no metadata, the file as it was
    copied = tmp_path / "copied"
    shutil.copytree(done, copied, ignore=shutil.ignore_patterns("dataset_metadata.json", ".collect.lock"))
    assert json.loads(collect_dataset(TINY, copied, progress=False).read_text())["complete"]
    assert all((copied / n).read_bytes() == (done / n).read_bytes() for n in names)


def _listing(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (hidden ones too) with its bytes."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_a_folder_of_the_users_own_hdf5_files_is_left_exactly_as_it_was(tmp_path: Path, capsys, monkeypatch):
    """``cicfw collect out_dir=<a folder of my .h5 files>``: one line, exit 2, and no ``.collect.lock`` (nor
    a removed ``.*.tmp``) left in the user's folder: the refusal comes before the lock is taken."""
    import cicfw.collect.app as collect_mod

    monkeypatch.setattr(dataset_mod, "run_episode", lambda *a, **k: pytest.fail("simulated"))
    mine = tmp_path / "mine"
    mine.mkdir()
    for i in range(3):
        (mine / f"data_{i:05d}.h5").write_bytes(b"my data %d" % i)
    (mine / ".notes.tmp").write_text("my notes")
    before = _listing(mine)
    with pytest.raises(SystemExit) as exc:
        collect_mod.run({**TINY, "out_dir": str(mine)})
    assert exc.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("cicfw: error: ") and str(mine) in lines[0], lines
    assert "data_00000.h5" in lines[0], lines  # names a file it would not mix in
    assert _listing(mine) == before
