"""bench/data_scale.py's train command passes on the training's exit status."""
from __future__ import annotations

import subprocess
import sys
from argparse import Namespace

import pytest

from conftest import load_bench_script


def test_a_failed_training_fails_the_bench(tmp_path, monkeypatch):
    """The training it starts stands in as a child that fails at once with cicfw's user-error status (what
    ``cicfw.train`` gives a data.path holding no HDF5 file): the bench exits with that status, not 0."""
    bench = load_bench_script("data_scale")
    real, started = subprocess.Popen, []

    def failing_training(cmd, **kwargs):
        started.append(cmd)
        return real([sys.executable, "-c", "import sys; print('cicfw: error: no data'); sys.exit(2)"], **kwargs)

    monkeypatch.setattr(bench.subprocess, "Popen", failing_training)
    args = Namespace(folder=tmp_path / "no_data", steps=1, workers=0, run_dir=str(tmp_path / "run"), overrides=[])
    with pytest.raises(SystemExit) as stop:
        bench.train(args)
    assert stop.value.code == 2 and started and started[0][1:3] == ["-m", "cicfw.train"]
