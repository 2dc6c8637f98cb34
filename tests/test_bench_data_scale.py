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


def test_write_refuses_a_folder_holding_files_it_did_not_write(tmp_path, monkeypatch):
    """``write`` skips names it finds: beside real data (named as its own files are) it would add random files."""
    from cicfw.core.errors import ConfigError
    from conftest import write_tiny_dataset

    bench = load_bench_script("data_scale")
    monkeypatch.setattr(bench, "FRAMES_PER_FILE", 4)
    real = write_tiny_dataset(tmp_path / "real", n_files=1, n=4)
    (real / next(real.iterdir()).name).rename(real / "data_00000.h5")
    with pytest.raises(ConfigError) as err:
        bench.write(real, 2, 0)
    assert (err.value.key, err.value.value) == ("folder", str(real))
    assert sorted(p.name for p in real.iterdir()) == ["data_00000.h5"]
    ours = tmp_path / "ours"
    bench.write(ours, 2, 0)
    bench.write(ours, 3, 0)  # a rerun finishes its own files
    assert len(list(ours.iterdir())) == 3
    with pytest.raises(ConfigError):
        bench.write(ours, 4, 1)  # another seed's files are not this run's
    afile = tmp_path / "afile"
    afile.write_text("mine\n")
    with pytest.raises(ConfigError) as err:  # was mkdir's FileExistsError traceback
        bench.write(afile, 1, 0)
    assert (err.value.key, err.value.value) == ("folder", str(afile)) and afile.read_text() == "mine\n"
