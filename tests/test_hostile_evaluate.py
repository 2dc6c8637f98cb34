"""``cicfw evaluate`` as a hostile user runs it: mistakes refused before any episode is
driven, Ctrl-C says what is kept, an unusable run folder is one line, and the report is readable by
the colleagues who share the results folder."""
from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from cicfw.benchmark.journal import LOG_NAME, read_log
from cicfw.core.config_checks import SchemaError
from cicfw.benchmark.app import compose_config, evaluate
from test_hostile_train import _errors, read_only_in_process
from conftest import assert_refused, run_app_in_process

pytestmark = pytest.mark.slow  # trains, collects, drives or runs an app (pytest -m "not slow" skips it)

TOWN = str(Path(__file__).parent / "data" / "bench_town.yaml")
QUICK = ("policy=expert", f"suite.towns=[{TOWN}]", "suite.weathers=[ClearNoon]", "suite.limit=2",
         "progress_bar=false", "runner.workers=1")


@pytest.mark.parametrize("override, key", [("+foo=1", "foo"), ("+vide=[0]", "vide")])
def test_an_unknown_top_level_key_is_refused_before_driving(tmp_path, override, key):
    with pytest.raises(SchemaError) as err:
        evaluate(compose_config([*QUICK, override]), tmp_path / "run")
    assert (err.value.kind, err.value.key) == ("unknown key", key), str(err.value)
    assert "video_max" in str(err.value) and "\n" not in str(err.value)  # the accepted keys
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("video, value, named", [  # named: what the line offers instead
    ("[nosuch]", "nosuch", "bench_town/ClearNoon/000"),
    ("[5]", 5, "0..1"),
])
def test_an_unknown_video_episode_is_refused_before_driving(tmp_path, video, value, named):
    with pytest.raises(ValueError) as err:
        evaluate(compose_config([*QUICK, f"video={video}"]), tmp_path / "run")
    assert err.value.value == value and "video" in str(err.value) and named in str(err.value), str(err.value)
    assert not (tmp_path / "run" / LOG_NAME).exists()  # not one episode driven


def test_report_files_are_readable_by_others_under_umask_022(tmp_path):
    from cicfw.core.sweeps import write_job_metrics

    old = os.umask(0o022)
    try:
        evaluate(compose_config([*QUICK, "video=[0]"]), tmp_path / "run")
        write_job_metrics(tmp_path / "run", {"closed_loop/success": 50.0})
    finally:
        os.umask(old)
    files = [p for p in (tmp_path / "run").rglob("*") if p.is_file() and p.name != ".lock"]
    names = {p.relative_to(tmp_path / "run").as_posix() for p in files}
    assert {"episodes.json", "episodes.csv", "summary.json", "table.md", "table.tex", "trajectories.npz",
            "success_bars.png", "metrics.json", LOG_NAME}.issubset(names), names
    assert any(n.startswith("map_") for n in names) and any(n.startswith("videos/") for n in names)
    modes = {n: oct(p.stat().st_mode & 0o777) for n, p in zip(names, files)}
    assert {n for n, p in zip(names, files) if p.stat().st_mode & 0o044 != 0o044} == set(), modes


def test_ctrl_c_during_the_evaluation_keeps_the_finished_episodes_and_says_how_to_go_on(tmp_path, monkeypatch):
    """The app run in this process (its handlers are put back after), Ctrl-C sent by the policy after 340
    episode-steps: a real SIGINT to this process, as a shell's Ctrl-C reaches the app."""
    import signal

    from cicfw.benchmark.builtin_policies import ExpertPolicy
    from cicfw.benchmark.policy import POLICIES

    class InterruptedExpert(ExpertPolicy):
        """The expert, until Ctrl-C after 340 episode-steps."""

        served = 0

        def act(self, obs):
            InterruptedExpert.served += len(obs)
            if InterruptedExpert.served > 340:
                os.kill(os.getpid(), signal.SIGINT)
            return super().act(obs)

    monkeypatch.setitem(POLICIES._entries, "interrupted_expert", InterruptedExpert)
    monkeypatch.setitem(POLICIES._origin, "interrupted_expert", "cicfw")
    out = tmp_path / "out"
    proc = run_app_in_process("cicfw.evaluate", *QUICK, "suite.limit=3", "runner.batch_size=1",
                              "policy.name=interrupted_expert", "maps=false", f"hydra.run.dir={out}",
                              env={"HYDRA_FULL_ERROR": "0"})
    assert proc.returncode == 130, proc.stderr[-3000:]
    kept = len(read_log(out)[1])
    assert 1 <= kept < 3
    assert _errors(proc) == [f"cicfw: interrupted; {kept} of 3 episodes finished, kept in {out}: run the same "
                             f"command with hydra.run.dir={out} to drive the rest"]
    assert json.loads((out / "summary.json").read_text())["complete"] is False


def test_a_read_only_run_folder_is_one_line(tmp_path, monkeypatch):
    proc = read_only_in_process(tmp_path, monkeypatch, "cicfw.evaluate", *QUICK, f"hydra.run.dir={tmp_path}/ro")
    assert_refused(proc, "hydra.run.dir", f"{tmp_path}/ro")


def test_a_300_character_run_name_is_one_line(tmp_path):
    name = "e" * 300
    proc = run_app_in_process("cicfw.evaluate", *QUICK, f"hydra.run.dir={tmp_path}/x/{name}",
                              env={"HYDRA_FULL_ERROR": "0"})
    assert "255" in assert_refused(proc, "hydra.run.dir", name[:20])  # the filesystem's limit


@pytest.mark.parametrize("override, key", [
    ("seed=abc", "seed"), ("suite.limit=abc", "suite.limit"), ("video_max=abc", "video_max"), ("video=3", "video"),
])
def test_a_value_of_the_wrong_type_is_refused_by_its_key_while_composing(tmp_path, override, key):
    """The schema names the key (int() alone says ``invalid literal for int() with base 10: 'abc'``)."""
    with pytest.raises(SchemaError) as err:
        compose_config([*QUICK, override])
    assert (err.value.kind, err.value.key) == ("wrong type", key), str(err.value)


@pytest.mark.parametrize("override, message", [
    ("suite.pairs=[0,x]", "suite.pairs must be a list of pair indices such as [0, 2] (or null for every pair), "
                          "got 'x'"),
    ("suite.pairs=3", "suite.pairs must be a list of pair indices such as [0, 2] (or null for every pair), got 3"),
])
def test_a_value_that_is_no_whole_number_is_refused_by_its_key(tmp_path, override, message):
    with pytest.raises(ValueError) as err:
        evaluate(compose_config([*QUICK, override]), tmp_path / "run")
    assert str(err.value) == message
    assert not (tmp_path / "run").exists()


def test_a_folder_without_checkpoints_is_named_as_given(tmp_path):
    """``checkpoint=<empty folder>`` printed ``checkpoint=PosixPath('...')``."""
    (tmp_path / "empty").mkdir()
    cfg = compose_config([*QUICK[1:], "policy=checkpoint", f"checkpoint={tmp_path}/empty"])
    with pytest.raises(ValueError) as err:
        evaluate(cfg, tmp_path / "run")
    assert (err.value.key, str(err.value.value)) == ("checkpoint", f"{tmp_path}/empty")
    assert "PosixPath" not in str(err.value)
    assert f"'{tmp_path}/empty'" in str(err.value)  # named as given
    assert not (tmp_path / "run").exists()


def test_a_python_caller_s_suite_typo_names_the_key_before_anything_is_written(tmp_path):
    """``evaluate_policy``'s suite dict is checked by the app's schema: a typo was a bare TypeError."""
    from cicfw.benchmark.app import evaluate_policy

    with pytest.raises(SchemaError) as err:
        evaluate_policy({"name": "expert"}, {"towns": ["town_a"], "weathers": ["ClearNoon"], "limt": 1}, None,
                        tmp_path / "out")
    assert err.value.key == "suite.limt" and "limit" in str(err.value)
    assert not (tmp_path / "out").exists()


def test_a_town_file_named_like_another_town_inside_gets_its_own_map(tmp_path):
    """Two towns driven in one run whose files carry one ``name:`` inside (a copy of a shipped town, edited)
    are two rows' towns, by their file stems: each gets its own map under that name, not one file both
    write."""
    import shutil

    copy = tmp_path / "my_town.yaml"
    shutil.copy(TOWN, copy)
    quick = [o for o in QUICK if not o.startswith("suite.towns=")]
    out = tmp_path / "run"
    evaluate(compose_config([*quick, f"suite.towns=[{TOWN},{copy}]", "suite.limit=1"]), out)
    assert sorted(p.name for p in out.glob("map_*.png")) == ["map_bench_town.png", "map_my_town.png"]


def test_a_town_file_too_long_for_its_map_name_is_refused_before_driving(tmp_path):
    """A town file's stem names its map (and videos): one the filesystem cannot take while the map is written
    is one line naming the town before any episode is driven, not a write error after the suite."""
    import shutil

    town = tmp_path / ("t" * 235 + ".yaml")  # a legal name, but not as map_<stem>.png's temporary name
    shutil.copy(TOWN, town)
    quick = [o for o in QUICK if not o.startswith("suite.towns=")]
    with pytest.raises(ValueError) as err:
        evaluate(compose_config([*quick, f"suite.towns=[{town}]"]), tmp_path / "run")
    assert err.value.key == "suite.towns" and err.value.value == town.stem, str(err.value)
    assert not (tmp_path / "run").exists()
