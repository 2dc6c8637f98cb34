"""Evaluation that survives a crash: finished episodes are kept as they finish, a rerun drives only the
missing ones and writes the report an uninterrupted run writes, a partial run is marked and refused by
the report, and a folder of another evaluation is never resumed into."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cicfw.benchmark import evaluation_report as report
from cicfw.benchmark.builtin_policies import ExpertPolicy
from cicfw.benchmark.journal import LOG_NAME, EpisodeLog, RunFolderError, read_log
from cicfw.benchmark.policy import POLICIES
from cicfw.benchmark.app import evaluate_policy, run_fingerprint
from conftest import assert_refused, process_alive, run_app_in_process

pytestmark = pytest.mark.slow  # trains, collects, drives or runs an app (pytest -m "not slow" skips it)

TOWN = str(Path(__file__).parent / "data" / "bench_town.yaml")
SUITE = {"towns": [TOWN], "weathers": ["ClearNoon", "MidRainyNoon"], "training_towns": [], "limit": 2}
RUNNER = {"workers": 1, "batch_size": 64}


class Boom(RuntimeError):
    """The simulated crash."""


class HalfExpert(ExpertPolicy):
    """The expert on even episodes, hard left on odd ones (so the report holds successes and failures);
    ``budget`` episode-steps are served before it raises (None: never); ``seen`` the episodes it drove."""

    budget: int | None = None
    seen: set = set()

    def act(self, obs):
        cls = type(self)
        if cls.budget is not None:
            if cls.budget < len(obs):
                raise Boom("simulated crash")
            cls.budget -= len(obs)
        cls.seen.update(int(e) for e in obs.episode)
        steer = super().act(obs)
        steer[obs.episode % 2 == 1] = -1.0
        return steer


if "test_half_expert" not in POLICIES:
    POLICIES.register("test_half_expert")(HalfExpert)
SPEC = {"name": "test_half_expert", "label": "half expert"}


def drive(out: Path, budget: int | None = None, **kw):
    HalfExpert.budget, HalfExpert.seen = budget, set()
    return evaluate_policy(SPEC, {**SUITE, **kw.pop("suite", {})}, {**RUNNER, **kw.pop("runner", {})}, out,
                           maps=False, **kw)


def report_files(out: Path) -> dict[str, object]:
    """Everything a run's report says about its episodes (not its wall time or how it was driven)."""
    data = json.loads((out / "episodes.json").read_text())
    summary = json.loads((out / "summary.json").read_text())
    summary.pop("wall_s")
    with np.load(out / "trajectories.npz") as z:
        trajs = {k: z[k] for k in z.files}
    return {"rows": data["episodes"], "csv": (out / "episodes.csv").read_text(), "summary": summary,
            "md": (out / "table.md").read_text(), "tex": (out / "table.tex").read_text(), "trajs": trajs}


def assert_same_report(a: Path, b: Path) -> None:
    ra, rb = report_files(a), report_files(b)
    for k in ("rows", "csv", "summary", "md", "tex"):
        assert ra[k] == rb[k], k
    assert sorted(ra["trajs"]) == sorted(rb["trajs"])
    for name in ra["trajs"]:
        assert np.array_equal(ra["trajs"][name], rb["trajs"][name]), name


@pytest.fixture(scope="module")
def whole(tmp_path_factory) -> tuple[Path, list[dict]]:
    """The uninterrupted run, and its rows."""
    out = tmp_path_factory.mktemp("whole") / "run"
    res = drive(out)
    assert res.driven == 4 and res.reused == 0 and res.summary["complete"] is True
    assert {r["reason"] for r in res.rows} > {"success"}  # successes and failures both
    return out, res.rows


def crash_budget(rows: list[dict]) -> tuple[int, int]:
    """Episode-steps after which the policy raises so that exactly the shortest episodes have finished
    (all run in lockstep), and how many those are."""
    steps = [int(r["steps"]) for r in rows]
    m = min(steps)
    assert max(steps) > m
    return len(steps) * m + 1, steps.count(m)


def test_a_crashed_suite_resumes_driving_only_the_missing_episodes(whole, tmp_path: Path):
    ref, rows = whole
    budget, finished = crash_budget(rows)
    out = tmp_path / "run"
    with pytest.raises(Boom):
        drive(out, budget)
    header, kept, trajs, _ = read_log(out)
    assert len(kept) == finished and sorted(trajs) == sorted(rows[i]["key"] for i in kept)
    # partial, and says so everywhere
    s = json.loads((out / "summary.json").read_text())
    assert s["complete"] is False and s["episodes"] == finished and s["episodes_total"] == 4
    assert json.loads((out / "episodes.json").read_text())["meta"]["complete"] is False
    assert f"**PARTIAL**: half expert had {finished} of 4 episodes" in (out / "table.md").read_text()
    assert f"half expert (PARTIAL {finished}/4)" in (out / "table.md").read_text()
    assert not (out / "trajectories.npz").exists()
    # the rerun drives exactly the missing episodes, and writes the uninterrupted run's report
    res = drive(out)
    assert (res.reused, res.driven) == (finished, 4 - finished)
    assert HalfExpert.seen == set(range(4)) - set(kept)
    assert res.summary["complete"] is True
    assert_same_report(ref, out)
    assert "PARTIAL" not in (out / "table.md").read_text()
    # a finished folder drives nothing and writes the same report again
    res = drive(out)
    assert (res.reused, res.driven) == (4, 0) and HalfExpert.seen == set()
    assert_same_report(ref, out)


def test_a_run_killed_part_way_leaves_a_table_counting_the_episodes_finished(tmp_path: Path, monkeypatch):
    """The run folder's own report is rewritten as episodes finish: what a kill (no handler runs) leaves after
    each episode counts the episodes its log holds, not the none of the run's start."""
    import cicfw.benchmark.app as app

    monkeypatch.setattr(app, "PARTIAL_REPORT_EVERY_S", 0.0)
    out, left = tmp_path / "run", []
    real = app.run

    def run(*args, on_episode, **kw):
        def finished(row, traj):
            on_episode(row, traj)  # what a kill right after this episode would leave on disk
            summary = json.loads((out / "summary.json").read_text())
            left.append((len(read_log(out, trajectories=False)[1]), summary["episodes"], summary["complete"],
                         (out / "table.md").read_text()))

        return real(*args, on_episode=finished, **kw)

    monkeypatch.setattr(app, "run", run)
    drive(out)
    assert [k for k, *_ in left] == [1, 2, 3, 4]
    for k, episodes, complete, md in left:
        assert episodes == k and complete is False
        assert f"had {k} of 4 episodes" in md and f"(PARTIAL {k}/4)" in md


@pytest.mark.parametrize("stopped_in", ["run", "bar_chart"])
def test_a_stop_after_the_last_episode_leaves_the_run_partial(whole, tmp_path: Path, monkeypatch, stopped_in):
    """Ctrl-C once the last episode is driven (as the runner returns, or while the pictures are written): the
    run does not look finished while its trajectories or pictures are missing, and the same call writes them,
    driving nothing."""
    from cicfw.benchmark import app
    from cicfw.core.errors import Interrupted

    ref, _ = whole
    out = tmp_path / "run"
    real = getattr(app, stopped_in)

    def stop(*args, **kwargs):
        if stopped_in == "run":
            real(*args, **kwargs)
        raise KeyboardInterrupt

    monkeypatch.setattr(app, stopped_in, stop)
    with pytest.raises(KeyboardInterrupt) as err:
        drive(out)
    assert isinstance(err.value, Interrupted) and str(out) in str(err.value)
    assert len(read_log(out)[1]) == 4  # every episode is kept
    assert json.loads((out / "summary.json").read_text())["complete"] is False
    assert not (out / "success_bars.png").exists()
    monkeypatch.setattr(app, stopped_in, real)
    res = drive(out)
    assert (res.reused, res.driven) == (4, 0) and res.summary["complete"] is True
    assert (out / "success_bars.png").is_file()
    assert_same_report(ref, out)


def test_a_torn_last_line_is_dropped_and_the_episode_driven_again(whole, tmp_path: Path):
    ref, rows = whole
    budget, finished = crash_budget(rows)
    out = tmp_path / "run"
    with pytest.raises(Boom):
        drive(out, budget)
    log = out / LOG_NAME
    good = log.read_bytes()
    torn = good.splitlines(keepends=True)[-1][:-40]  # the start of a line, cut off by a kill
    log.write_bytes(good + torn.replace(b'"episode": ', b'"episode": 9', 1))
    assert len(read_log(out)[1]) == finished
    res = drive(out)
    assert (res.reused, res.driven) == (finished, 4 - finished)
    assert_same_report(ref, out)
    lines = log.read_bytes().splitlines()
    assert len(lines) == 1 + 4 and all(json.loads(x) for x in lines)  # header + one per episode, nothing torn
    assert len(read_log(out)[1]) == 4  # a later resume finds every episode


def test_resuming_with_worker_processes_and_another_batch_size(tmp_path: Path):
    """Batch size and workers decide the speed only: a run stopped after two episodes and resumed
    with two worker processes (episodes reach the log through their queue) writes the same report."""
    spec = {"name": "expert"}
    whole = tmp_path / "whole"
    evaluate_policy(spec, SUITE, {"workers": 1}, whole, maps=False)
    out = tmp_path / "run"
    out.mkdir()
    lines = (whole / LOG_NAME).read_bytes().splitlines(keepends=True)
    (out / LOG_NAME).write_bytes(b"".join(lines[:3]))  # header + two episodes: a run killed after two
    res = evaluate_policy(spec, SUITE, {"workers": 2, "batch_size": 1}, out, maps=False)
    assert (res.reused, res.driven) == (2, 2)
    assert len(read_log(out)[1]) == 4
    assert_same_report(whole, out)


def test_an_episode_does_not_depend_on_the_episodes_beside_it(tmp_path: Path):
    """The simulator and the renderer keep no state across episodes: an episode driven alone or with
    others (in one lockstep batch, sharing one renderer) gives the same row and trajectory, so the
    episodes a resume drives are the ones an uninterrupted run drives."""
    from cicfw.benchmark.policy import Observations, Policy
    from cicfw.benchmark.runner import RunnerConfig, run
    from cicfw.benchmark.suite import build_suite, make_backend

    class Looker(Policy):  # steers from its image, row by row (so the policy itself is batch-independent)
        cameras = ("centre",)
        label = "looker"

        def act(self, obs: Observations) -> np.ndarray:
            img = obs.images["centre"].astype(np.float64)
            left, right = img[:, 40:, :100].mean(axis=(1, 2, 3)), img[:, 40:, 100:].mean(axis=(1, 2, 3))
            return np.clip((right - left) / 40.0, -1, 1)

    backend = make_backend(None)
    eps = build_suite(backend, [TOWN], ["MidRainyNoon"], limit=3)
    cfg = RunnerConfig(workers=1, batch_size=2, progress_bar=False)
    together = run(eps, Looker(), backend, cfg)
    alone = run([eps[1]], Looker(), backend, cfg)
    assert alone.rows[0] == together.rows[1]
    a, b = alone.trajectories[eps[1].key], together.trajectories[eps[1].key]
    assert sorted(a) == sorted(b) and all(np.array_equal(a[k], b[k]) for k in a)


# ------------------------------------------------------------------------------------------------
# another configuration, another writer


def test_a_folder_of_another_evaluation_is_refused_in_one_line(whole, tmp_path: Path):
    ref, _ = whole
    files = lambda: {p.name: p.read_bytes() for p in ref.iterdir() if p.is_file() and p.name[0] != "."}  # noqa: E731
    before = files()
    cases = [  # what changes, and the key and value (now) the refusal names
        (dict(), "policy.name", "expert"),
        (dict(suite={"weathers": ["ClearNoon"]}), "suite.weathers", ["ClearNoon"]),
        (dict(seed=3), "seed", 3),
        (dict(sim={"name": "embedded", "success_radius": 3.0}), "sim.success_radius", 3.0),
        (dict(runner={"off_road_s": 1.0}), "runner.off_road_s", 1.0),
    ]
    for kw, key, value in cases:
        spec = {"name": "expert"} if not kw else SPEC
        with pytest.raises(RunFolderError) as err:
            HalfExpert.budget = None
            evaluate_policy(spec, {**SUITE, **kw.pop("suite", {})}, {**RUNNER, **kw.pop("runner", {})}, ref,
                            maps=False, **kw)
        msg = str(err.value)
        assert (err.value.key, err.value.value) == (key, value) and key in msg, msg
        assert "\n" not in msg and str(ref) in msg, msg
    assert files() == before  # nothing touched


def test_the_app_refuses_with_its_own_hint(whole):
    ref, _ = whole
    from conftest import run_app_in_process

    proc = run_app_in_process("cicfw.evaluate", "policy=constant", f"suite.towns=[{TOWN}]", "suite.limit=2",
                              "progress_bar=false", f"hydra.run.dir={ref}")
    assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert "hydra.run.dir=<new folder>" in assert_refused(proc, "policy.name", ref)  # the app's own hint


def test_a_checkpoint_counts_by_its_contents_not_its_path(tmp_path: Path):
    from cicfw.benchmark.runner import RunnerConfig

    a = tmp_path / "a.ckpt"
    a.write_bytes(b"weights one")
    cfg = RunnerConfig(progress_bar=False)
    fp1, info = run_fingerprint({"name": "checkpoint", "checkpoint": str(a), "device": "cpu"}, SUITE, {"name": "embedded"},
                                cfg, [])
    assert info == {"checkpoint": str(a.resolve())} and "checkpoint" not in fp1["policy"]
    moved = tmp_path / "moved.ckpt"
    a.rename(moved)
    fp2, _ = run_fingerprint({"name": "checkpoint", "checkpoint": str(moved), "device": "cuda"}, SUITE,
                             {"name": "embedded"}, RunnerConfig(batch_size=7, workers=2, progress_bar=False), [])
    assert fp2 == fp1  # same file contents; device, batch size and workers do not count
    moved.write_bytes(b"weights two")  # e.g. last.ckpt overwritten by more training
    fp3, _ = run_fingerprint({"name": "checkpoint", "checkpoint": str(moved)}, SUITE, {"name": "embedded"}, cfg, [])
    with EpisodeLog.open(tmp_path / "run", fp1):
        pass
    with pytest.raises(RunFolderError) as err:
        EpisodeLog.open(tmp_path / "run", fp3)
    assert err.value.key == "policy.checkpoint_sha256"


def test_a_second_writer_is_refused(tmp_path: Path):
    fp = {"policy": {"name": "expert"}}
    with EpisodeLog.open(tmp_path / "run", fp):
        with pytest.raises(RunFolderError) as err:
            EpisodeLog.open(tmp_path / "run", fp)
        assert err.value.value == tmp_path / "run" and f"pid {os.getpid()}" in str(err.value)
    EpisodeLog.open(tmp_path / "run", fp).close()  # free again


def test_a_report_folder_without_a_log_is_not_overwritten(whole, tmp_path: Path):
    ref, _ = whole
    old = tmp_path / "old"
    old.mkdir()
    data = json.loads((ref / "episodes.json").read_text())
    data["meta"].pop("fingerprint")  # written by a cicfw before episode logs
    (old / "episodes.json").write_text(json.dumps(data))
    with pytest.raises(RunFolderError) as err:
        drive(old)
    assert err.value.key == "out_dir" and str(err.value.value) == str(old)
    assert not (old / LOG_NAME).exists()


# ------------------------------------------------------------------------------------------------
# the report and a killed process


def test_the_report_refuses_a_partial_run_unless_asked(whole, tmp_path: Path, capsys):
    ref, rows = whole
    budget, finished = crash_budget(rows)
    out = tmp_path / "sweep" / "0"
    with pytest.raises(Boom):
        drive(out, budget, label="crashed")
    assert report.main([str(tmp_path / "sweep"), "--no-plots"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith("cicfw: error: ") and str(out) in err, err
    assert f"{finished} of 4" in err and "--partial" in err, err  # what is finished, and the option that takes it
    assert report.main([str(tmp_path / "sweep"), str(ref), "--partial", "--no-plots", "--out", str(tmp_path / "j")]) == 0
    md = (tmp_path / "j" / "table.md").read_text()
    assert f"**PARTIAL**: crashed had {finished} of 4 episodes" in md
    assert f"| crashed (PARTIAL {finished}/4) |" in md and "| half expert |" in md
    csv = (tmp_path / "j" / "table.csv").read_text()
    assert f"\ncrashed (PARTIAL {finished}/4)," in csv and "\nhalf expert," in csv


#: a policy that SIGKILLs its own process after KILL_AFTER_STEPS episode-steps (unset or empty: never)
KILLING_EXPERT = """
import os, signal
from cicfw.benchmark.builtin_policies import ExpertPolicy
from cicfw.benchmark.policy import POLICIES

class KillingExpert(ExpertPolicy):
    served = 0

    def act(self, obs):
        budget = os.environ.get("KILL_AFTER_STEPS")
        KillingExpert.served += len(obs)
        if budget and KillingExpert.served > int(budget):
            os.kill(os.getpid(), signal.SIGKILL)  # as `kill -9` from outside: no handler, no cleanup
        return super().act(obs)

if "killing_expert" not in POLICIES:
    POLICIES.register("killing_expert")(KillingExpert)
"""
#: ``python -m cicfw.evaluate`` with the killing expert known to it
KILLER = KILLING_EXPERT + """
from cicfw.benchmark.app import main
main()
"""


def test_a_sigkilled_evaluation_resumes_with_the_same_command(tmp_path: Path):
    """Only the killed run needs a process of its own (killed from inside, as ``kill -9``): the uninterrupted
    run and the rerun are the same command run in this interpreter, with the killing expert known here too."""
    script = tmp_path / "evaluate_killable.py"
    script.write_text(KILLER)
    exec(KILLING_EXPERT, {})  # registers killing_expert here (once), never killing: KILL_AFTER_STEPS unset
    args = ["policy=expert", "policy.name=killing_expert", f"suite.towns=[{TOWN}]",
            "suite.weathers=[ClearNoon,MidRainyNoon]", "suite.limit=3", "progress_bar=false", "maps=false",
            "runner.workers=1"]

    proc = run_app_in_process("cicfw.evaluate", *args, f"hydra.run.dir={tmp_path / 'whole'}",
                              env={"KILL_AFTER_STEPS": None})
    assert proc.returncode == 0, proc.stderr[-2000:]
    rows = json.loads((tmp_path / "whole" / "episodes.json").read_text())["episodes"]
    budget, finished = crash_budget(rows)
    out = tmp_path / "killed"
    proc = subprocess.run([sys.executable, str(script), *args, f"hydra.run.dir={out}"], capture_output=True,
                          text=True, env={**os.environ, "KILL_AFTER_STEPS": str(budget)})
    assert proc.returncode == -signal.SIGKILL
    assert len(read_log(out)[1]) == finished
    assert json.loads((out / "summary.json").read_text())["complete"] is False  # written before driving
    assert report.main([str(out), "--no-plots"]) == 2
    proc = run_app_in_process("cicfw.evaluate", *args, f"hydra.run.dir={out}", env={"KILL_AFTER_STEPS": None})
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert f"{finished} kept from an earlier run, {len(rows) - finished} to drive" in proc.stdout + proc.stderr
    assert_same_report(tmp_path / "whole", out)


ORPHAN = """
import multiprocessing as mp, sys, time

def child():
    from cicfw.benchmark.runner import _exit_with_parent
    _exit_with_parent(0.1)
    time.sleep(120)

if __name__ == "__main__":
    p = mp.get_context("spawn").Process(target=child, daemon=True)
    p.start()
    print(p.pid, flush=True)  # killed now: most likely before the child has imported cicfw and started its watch
    time.sleep(120)
"""


def test_worker_processes_end_when_their_evaluation_is_killed(tmp_path: Path):
    """A SIGKILLed evaluation leaves no worker driving on (the rerun would race it for the log)."""
    import time

    script = tmp_path / "parent.py"
    script.write_text(ORPHAN)
    parent = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    child = 0
    try:
        child = int(parent.stdout.readline())
        assert process_alive(child)
        parent.send_signal(signal.SIGKILL)
        parent.wait()
        deadline = time.monotonic() + 10
        while process_alive(child) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not process_alive(child)
    finally:
        parent.kill()
        if child and process_alive(child):
            os.kill(child, signal.SIGKILL)




def test_a_hard_linked_copy_resumes_into_a_log_of_its_own(tmp_path: Path):
    """``cp -al`` of a stopped evaluation shares its episode log's file: resuming the copy appended to the
    original folder's log too, which then held episodes it never drove."""
    fp = {"policy": {"name": "expert"}}
    row = {"episode": 0, "key": "town_a/ClearNoon/000"}
    with EpisodeLog.open(tmp_path / "a", fp) as log:
        log.add(row, {"x": np.zeros(3)})
    before = (tmp_path / "a" / "episodes.jsonl").read_bytes()
    (tmp_path / "b").mkdir()
    os.link(tmp_path / "a" / "episodes.jsonl", tmp_path / "b" / "episodes.jsonl")
    with EpisodeLog.open(tmp_path / "b", fp) as log:
        assert sorted(log.rows) == [0]
        log.add({"episode": 1, "key": "town_a/ClearNoon/001"}, {"x": np.ones(3)})
    assert (tmp_path / "a" / "episodes.jsonl").read_bytes() == before
    assert (tmp_path / "b" / "episodes.jsonl").read_bytes().startswith(before)
    assert len((tmp_path / "b" / "episodes.jsonl").read_bytes().splitlines()) == 3  # header and two episodes
