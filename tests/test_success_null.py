"""An evaluation stopped before its first episode finished has no success rate: summary.json says
``"success": null`` (not 0.0, which reads as a model that failed everything), and everything that reads
a summary's ``success`` takes the null: the app's log, ``EvalResult.success``, the evaluation after
training's metrics, the joined report and the reproduction's learning curve."""
from __future__ import annotations

import json
import logging
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from cicfw.benchmark import evaluation_report as report
from cicfw.benchmark.finished_run import Run
from cicfw.core.errors import Interrupted
from cicfw.benchmark.app import EvalResult, evaluate_policy, percent

TOWN = str(Path(__file__).parent / "data" / "bench_town.yaml")
SUITE = {"towns": [TOWN], "weathers": ["ClearNoon"], "training_towns": [], "limit": 1}


def _row(success: bool, town_set: str = "new", weather_set: str = "training") -> dict:
    return {"episode": 0, "key": "t/ClearNoon/000", "town_set": town_set, "weather_set": weather_set,
            "command": "left", "success": success, "reason": "success" if success else "timeout", "steps": 10}


def test_no_episodes_no_rate():
    assert Run("m", []).success_rate() is None
    s = report.summary(Run("m", [], meta={"complete": False, "episodes_total": 8}))
    assert s["success"] is None and s["episodes"] == 0 and s["cells"] == {} and s["manoeuvres"] == {}
    assert report.summary(Run("m", [_row(False)]))["success"] == 0.0  # a driven failure is a rate of 0
    assert report.summary(Run("m", [_row(True), _row(False)]))["success"] == 50.0


def test_eval_result_and_log_take_the_null(tmp_path):
    res = EvalResult(summary={"success": None, "cells": {}}, rows=[], run_dir=tmp_path, driven=0, reused=0)
    assert res.success is None
    assert percent(None) == "none (no episodes)" and percent(72.5) == "72.50%"


def test_an_evaluation_stopped_before_any_episode_writes_null(tmp_path, monkeypatch):
    import cicfw.benchmark.app as app

    def stopped(*args, **kwargs):
        raise KeyboardInterrupt  # Ctrl-C (or SIGTERM, which the apps turn into one) before an episode finished

    monkeypatch.setattr(app, "run", stopped)  # the runner's run, as the app imported it
    with pytest.raises(Interrupted) as err:
        evaluate_policy({"name": "expert"}, SUITE, {"workers": 1}, tmp_path / "run")
    assert str(err.value).startswith("0 of ")
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["success"] is None and summary["episodes"] == 0 and summary["complete"] is False
    # the joined report (what `cicfw report --partial` and a sweep's table read) shows the run as PARTIAL, no rate
    md = report.write_joined(report.find_runs([tmp_path / "run"], partial="include"), tmp_path / "joined", plots=True)
    assert "(PARTIAL 0/" in md and "| – | – | – | – |" in md


def test_after_training_metrics_leave_out_a_missing_rate(tmp_path, monkeypatch):
    import cicfw.benchmark.app as evaluate

    monkeypatch.setattr(evaluate, "evaluate_checkpoint",
                        lambda *a, **k: {"success": None, "cells": {}})
    trainer = SimpleNamespace(checkpoint_callbacks=[], fast_dev_run=False, logger=None, global_step=0,
                              save_checkpoint=lambda p: Path(p).parent.mkdir(parents=True, exist_ok=True))
    cfg = SimpleNamespace(get=lambda key, default=None: None)
    evaluate.evaluate_after_training(cfg, trainer, tmp_path)
    assert json.loads((tmp_path / "metrics.json").read_text()) == {}


def test_a_curve_point_without_every_column_has_no_overall(tmp_path):
    from cicfw.reproduction.app import _curve_point
    from cicfw.reproduction.report import curve_points

    ckpt = tmp_path / "epoch001.ckpt"
    torch.save({"epoch": 0, "global_step": 3}, ckpt)
    one = {"cells": {"training_town/training_weathers": {"rate": 80.0}}}
    point = _curve_point(ckpt, one, batch=8, accumulate=1)
    assert point["overall"] is None and point["samples"] == 24  # not 80 / 4 = 20: three columns have no rate
    full = {"cells": {c: {"rate": 40.0} for c in ("training_town/training_weathers", "training_town/new_weathers",
                                                   "new_town/training_weathers", "new_town/new_weathers")}}
    assert _curve_point(ckpt, full, batch=8, accumulate=1)["overall"] == 40.0
    data = {"rows": [{"label": "CIL", "curve": {"0": [point, {**point, "samples": 48, "overall": 50.0}]}}]}
    assert curve_points(data) == {"CIL": [(48, 50.0, 50.0, 50.0, 1)]}
