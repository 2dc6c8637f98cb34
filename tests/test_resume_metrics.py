"""A run resumed in its own folder keeps the metrics it logged before the resume."""
from __future__ import annotations

import csv

from cicfw.train.app import LOGGERS


def test_a_resumed_runs_earlier_metrics_are_kept(tmp_path):
    for run in range(3):  # the first run, then two resumes in the same folder
        logger = LOGGERS["csv"](tmp_path)
        logger.log_metrics({"train/loss": float(run)}, step=run)
        logger.finalize("success")
    files = [tmp_path / "csv" / name for name in ("metrics.1.csv", "metrics.2.csv", "metrics.csv")]
    steps = [[row["step"] for row in csv.DictReader(f.open())] for f in files]
    assert steps == [["0"], ["1"], ["2"]]  # every run's rows, each in its own file
