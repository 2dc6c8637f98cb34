"""``.evaluate.lock`` exists only while an evaluation writes its folder: a finished evaluation, and one
stopped before its first episode, leave none behind (the next command on the folder finds no holder)."""
from __future__ import annotations

from pathlib import Path

import pytest

from cicfw.benchmark.journal import LOCK_NAME
from cicfw.core.errors import Interrupted
from cicfw.benchmark.app import evaluate_policy

pytestmark = pytest.mark.slow  # drives the suite (one episode)

TOWN = str(Path(__file__).parent / "data" / "bench_town.yaml")
SUITE = {"towns": [TOWN], "weathers": ["ClearNoon"], "training_towns": [], "limit": 1}


def test_a_finished_evaluation_leaves_no_lock(tmp_path):
    res = evaluate_policy({"name": "expert"}, SUITE, {"workers": 1}, tmp_path / "run", maps=False)
    assert res.summary["complete"] and res.driven == 1
    assert not (tmp_path / "run" / LOCK_NAME).exists()
    assert sorted(p.name for p in (tmp_path / "run").iterdir() if p.name.startswith(".")) == []


def test_a_stopped_evaluation_leaves_no_lock(tmp_path, monkeypatch):
    import cicfw.benchmark.app as app

    def stopped(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(app, "run", stopped)  # the runner's run, as the app imported it
    with pytest.raises(Interrupted):
        evaluate_policy({"name": "expert"}, SUITE, {"workers": 1}, tmp_path / "run")
    assert not (tmp_path / "run" / LOCK_NAME).exists()
