"""Two runs into one output at once: the run refused leaves the other's files as they are, byte for byte.
Each race is made certain: the other run takes the folder (its lock, its files) right after this run's
checks, from a process of its own, before this run would take it."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from cicfw.core.files import write_together
from conftest import assert_refused, run_app_in_process

ENV = {"HYDRA_FULL_ERROR": "0"}

#: the other run: holds its app's lock in ``<run>`` (``.<app>.lock`` unless named) and writes its files, then waits
OTHER = """
import json, sys, time
from pathlib import Path
from cicfw.core.locks import FolderLock
run, lock, files = Path(sys.argv[1]), sys.argv[2], json.loads(sys.argv[3])
class Lock(FolderLock):
    lock_name = lock
Lock(run).acquire()
for rel, text in files.items():
    (run / rel).parent.mkdir(parents=True, exist_ok=True)
    (run / rel).write_text(text)
print("held", flush=True)
time.sleep(120)
"""


@pytest.fixture
def other_run_after_the_checks(monkeypatch):
    """``start(run, app, files, lock=None)``: once this process's run-folder checks pass (``RunFolderCheck``),
    another process takes ``run`` for ``app`` (its lock file ``lock``, else ``.<app>.lock``) and writes ``files``
    there; returns those files' bytes by path."""
    from cicfw.core import run_folder

    procs = []
    started = {}

    def start(run: Path, app: str, files: dict[str, str], lock: str | None = None) -> dict[Path, bytes]:
        original = run_folder.RunFolderCheck.on_run_start

        def then_the_other(self, config, **kwargs):
            original(self, config, **kwargs)
            p = subprocess.Popen([sys.executable, "-c", OTHER, str(run), lock or f".{app}.lock", json.dumps(files)],
                                 stdout=subprocess.PIPE, text=True)
            procs.append(p)
            assert p.stdout.readline().strip() == "held"
            started["yes"] = True

        monkeypatch.setattr(run_folder.RunFolderCheck, "on_run_start", then_the_other)
        return {run / rel: text.encode() for rel, text in files.items()}

    yield start
    for p in procs:
        p.kill()
        p.wait()
    assert started, "the other run never started"


def _files(run: Path, lock: str) -> dict[Path, bytes]:
    return {p: p.read_bytes() for p in run.rglob("*") if p.is_file() and p.name != lock}


@pytest.mark.slow  # runs the app (in this process)
def test_an_evaluation_refused_for_a_folder_another_took_after_its_checks_leaves_its_files(
        tmp_path, other_run_after_the_checks):
    run = tmp_path / "run"
    theirs = other_run_after_the_checks(run, "evaluate", {
        ".hydra/config.yaml": "seed: 0\n", ".hydra/overrides.yaml": "- seed=0\n",
        ".hydra/hydra.yaml": "hydra:\n  job:\n    name: evaluate\n", "evaluate.log": "their log\n",
        "episodes.jsonl": '{"format": "cicfw-episode-log/1"}\n'})
    proc = run_app_in_process("cicfw.evaluate", "policy=expert", "suite.limit=1", "seed=1",
                              f"hydra.run.dir={run}", env=ENV)
    assert_refused(proc, str(run))
    assert _files(run, ".evaluate.lock") == theirs


@pytest.mark.slow  # runs the app (in this process)
def test_a_diagnosis_refused_for_a_folder_another_took_after_its_checks_leaves_its_files(
        tmp_path, other_run_after_the_checks):
    run = tmp_path / "run"
    (tmp_path / "bad.ckpt").write_bytes(b"not a checkpoint")
    theirs = other_run_after_the_checks(run, "diagnose", {
        ".hydra/config.yaml": "checkpoint: a.ckpt\n", ".hydra/overrides.yaml": "- checkpoint=a.ckpt\n",
        ".hydra/hydra.yaml": "hydra:\n  job:\n    name: diagnose\n", "diagnose.log": "their log\n",
        "steer_diagnostic.json": "{}\n"})
    proc = run_app_in_process("cicfw.diagnose", f"checkpoint={tmp_path / 'bad.ckpt'}", f"hydra.run.dir={run}",
                              env=ENV)
    assert_refused(proc, "hydra.run.dir", str(run))
    assert _files(run, ".diagnose.lock") == theirs


@pytest.mark.slow  # runs the app (in this process)
def test_a_collect_refused_for_a_run_folder_another_collect_took_after_its_checks_leaves_its_files(
        tmp_path, other_run_after_the_checks):
    """Two collects into one hydra.run.dir with different out_dirs: the second is refused in one line and
    writes neither that folder's .hydra record nor its own dataset."""
    from cicfw.collect.lock import RUN_LOCK_NAME

    run = tmp_path / "run"
    theirs = other_run_after_the_checks(run, "collect", {
        ".hydra/config.yaml": "out_dir: a\n", ".hydra/overrides.yaml": "- out_dir=a\n",
        ".hydra/hydra.yaml": "hydra:\n  job:\n    name: collect\n", "collect.log": "their log\n"},
        lock=RUN_LOCK_NAME)
    proc = run_app_in_process("cicfw.collect", f"out_dir={tmp_path / 'b'}", f"hydra.run.dir={run}", "episodes=1",
                              "seconds=1", "workers=0", "weathers=[ClearNoon]", "cameras=[centre]", env=ENV)
    assert_refused(proc, "hydra.run.dir", str(run))
    assert _files(run, RUN_LOCK_NAME) == theirs
    assert not (tmp_path / "b").exists()


def test_a_training_refused_for_a_folder_another_took_after_its_checks_leaves_its_files(
        tmp_path, other_run_after_the_checks, capsys):
    from omegaconf import OmegaConf

    from cicfw.core.run_folder import TrainRunFolderCheck

    run = tmp_path / "run"
    theirs = other_run_after_the_checks(run, "train", {
        ".hydra/config.yaml": "seed: 0\n", ".hydra/hydra.yaml": "hydra:\n  job:\n    name: train\n",
        "train.log": "their log\n"})
    config = OmegaConf.create({"ckpt_path": None, "hydra": {"run": {"dir": str(run)}, "job": {"name": "train"}}})
    with pytest.raises(SystemExit) as stop:
        TrainRunFolderCheck().on_run_start(config)
    assert stop.value.code == 2
    line = capsys.readouterr().err.strip()
    assert line.startswith("cicfw: error:") and str(run) in line and "hydra.run.dir" in line, line
    assert _files(run, ".train.lock") == theirs


@pytest.mark.slow  # runs the app twice (in this process)
def test_a_diagnosis_holds_its_folder_only_while_it_runs(tmp_path):
    """No lock file is left behind: the same command is refused for the checkpoint, not the folder."""
    run = tmp_path / "run"
    (tmp_path / "bad.ckpt").write_bytes(b"not a checkpoint")
    for _ in range(2):
        proc = run_app_in_process("cicfw.diagnose", f"checkpoint={tmp_path / 'bad.ckpt'}",
                                  f"hydra.run.dir={run}", env=ENV)
        assert_refused(proc, "bad.ckpt")
        assert not run.exists()  # a folder made for a refused run goes, its lock with it


def test_a_name_to_be_created_is_never_replaced_and_the_files_made_before_go_again(tmp_path):
    first, second = tmp_path / "a.json", tmp_path / "b.bin"

    def another_writes_the_second():
        second.write_bytes(b"theirs")

    with pytest.raises(FileExistsError) as err:
        write_together({first: b"mine a", second: b"mine b"}, new=[first, second],
                       before_rename=another_writes_the_second)
    assert err.value.filename == str(second)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.bin"]  # no temporary file, no half of this write
    assert second.read_bytes() == b"theirs"
    write_together({first: b"mine a", second: b"mine b"}, new=[first])  # a name found at the check: replaced
    assert (first.read_bytes(), second.read_bytes()) == (b"mine a", b"mine b")


@pytest.mark.parametrize("job", ["diagnose", "evaluate"])
def test_a_run_folder_given_relative_lets_go_of_its_lock_in_the_folder_hydra_moved_into(tmp_path, monkeypatch, job):
    """hydra.run.dir=rel/run with hydra.job.chdir=true: the app lets go of the lock from inside the run folder
    (by Hydra's absolute output_dir); the lock file goes, so the next run finds no stale lock there."""
    from omegaconf import OmegaConf

    from cicfw.benchmark.journal import EvaluateRunFolderCheck
    from cicfw.core.run_folder import LockedRunFolderCheck, release_folder_locks

    monkeypatch.chdir(tmp_path)
    config = OmegaConf.create({"hydra": {"run": {"dir": "rel/run"}, "job": {"name": job}}})
    check = EvaluateRunFolderCheck() if job == "evaluate" else LockedRunFolderCheck()
    check.on_run_start(config)
    run, lock = tmp_path / "rel" / "run", tmp_path / "rel" / "run" / f".{job}.lock"
    assert lock.is_file()
    monkeypatch.chdir(run)  # hydra.job.chdir=true: the job runs inside its folder
    release_folder_locks(run)  # as the app does when it finishes, with Hydra's runtime.output_dir
    assert not lock.exists()
    monkeypatch.chdir(tmp_path)  # Hydra moves back before the run ends
    check.on_run_end(config)


@pytest.mark.parametrize("job", ["train", "diagnose", "evaluate"])
def test_a_run_folder_made_for_a_run_whose_lock_cannot_be_used_goes_again(tmp_path, monkeypatch, capsys, job):
    """A file system without flock: the run is one line naming hydra.run.dir, and the folder made for it (its
    parents too) is gone, not left holding a lock file."""
    import errno

    from omegaconf import OmegaConf

    from cicfw.benchmark.journal import EvaluateRunFolderCheck
    from cicfw.core import locks
    from cicfw.core.run_folder import LockedRunFolderCheck, TrainRunFolderCheck

    def no_flock(fd, op):
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(locks.fcntl, "flock", no_flock)
    run = tmp_path / "made" / "run"
    config = OmegaConf.create({"ckpt_path": None, "hydra": {"run": {"dir": str(run)}, "job": {"name": job}}})
    check = {"train": TrainRunFolderCheck, "diagnose": LockedRunFolderCheck, "evaluate": EvaluateRunFolderCheck}[job]
    with pytest.raises(SystemExit) as stop:
        check().on_run_start(config)
    assert stop.value.code == 2
    line = capsys.readouterr().err.strip()
    assert line.startswith("cicfw: error:") and "hydra.run.dir" in line and str(run) in line, line
    assert not (tmp_path / "made").exists()


@pytest.mark.parametrize("job", ["diagnose", "evaluate"])
def test_a_folder_another_run_just_made_and_holds_is_left_to_it(tmp_path, monkeypatch, capsys, job):
    """The other run made the folder and took its lock after this run's checks, before writing anything: this
    run is refused, and the folder and the other's lock stay."""
    from omegaconf import OmegaConf

    from cicfw.benchmark.journal import EvaluateRunFolderCheck, RunFolderLock
    from cicfw.core import run_folder
    from cicfw.core.run_folder import AppFolderLock, LockedRunFolderCheck

    run = tmp_path / "made" / "run"
    other = RunFolderLock(run) if job == "evaluate" else AppFolderLock(run, job)
    original = run_folder.RunFolderCheck.on_run_start

    def then_the_other(self, config, **kwargs):
        original(self, config, **kwargs)
        other.acquire()

    monkeypatch.setattr(run_folder.RunFolderCheck, "on_run_start", then_the_other)
    config = OmegaConf.create({"hydra": {"run": {"dir": str(run)}, "job": {"name": job}}})
    check = EvaluateRunFolderCheck() if job == "evaluate" else LockedRunFolderCheck()
    try:
        with pytest.raises(SystemExit) as stop:
            check.on_run_start(config)
        assert stop.value.code == 2
        assert str(run) in capsys.readouterr().err
        assert other.path.is_file()
    finally:
        other.release()


@pytest.mark.parametrize("job, other, files", [
    ("diagnose", "train", {".hydra/hydra.yaml": "hydra:\n  job:\n    name: train\n", "train.log": "their log\n"}),
    ("train", "evaluate", {".hydra/hydra.yaml": "hydra:\n  job:\n    name: evaluate\n",
                           "episodes.jsonl": '{"format": "cicfw-episode-log/1"}\n'}),
])
def test_a_folder_another_app_took_after_the_checks_is_refused_once_held(tmp_path, other_run_after_the_checks,
                                                                         capsys, job, other, files):
    """Another app's run (its own lock) takes the folder between this run's checks and its lock: the check
    is made again under the lock, so this run is refused in one line and Hydra never writes over its files."""
    from omegaconf import OmegaConf

    from cicfw.core.run_folder import LockedRunFolderCheck, TrainRunFolderCheck

    run = tmp_path / "run"
    theirs = other_run_after_the_checks(run, other, files)
    config = OmegaConf.create({"ckpt_path": None, "hydra": {"run": {"dir": str(run)}, "job": {"name": job}}})
    with pytest.raises(SystemExit) as stop:
        (TrainRunFolderCheck() if job == "train" else LockedRunFolderCheck()).on_run_start(config)
    assert stop.value.code == 2
    line = capsys.readouterr().err.strip()
    assert line.startswith("cicfw: error:") and "hydra.run.dir" in line and str(run) in line, line
    assert _files(run, f".{other}.lock") == theirs
    assert not (run / f".{job}.lock").exists()
