"""bench/data_scale.py's train command passes on the training's exit status."""
from __future__ import annotations

from argparse import Namespace

import pytest

from conftest import load_bench_script


def test_a_failed_training_fails_the_bench(tmp_path):
    bench = load_bench_script("data_scale")
    args = Namespace(folder=tmp_path / "no_data", steps=1, workers=0, run_dir=str(tmp_path / "run"), overrides=[])
    with pytest.raises(SystemExit) as stop:
        bench.train(args)
    assert stop.value.code == 2  # cicfw train's refusal of a data.path holding no HDF5 file
