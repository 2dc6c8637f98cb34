"""Third-party plugins: the example package trains by name, is listed with its distribution, and a
broken plugin is reported and skipped while the built-ins keep working.

Needs the example plugin installed: ``pip install ./plugins/cicfw-attention-mixer`` (.ci/run does).
"""
from __future__ import annotations

from importlib.metadata import version

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch
import yaml

from cicfw.model.mixers import Mixer
from cicfw.registry import MIXERS, listing, main
from cicfw.testing import check_head, check_mixer
from cicfw.train.app import train
from conftest import assert_refused, compose_train, run_app_in_process

pytestmark = pytest.mark.slow  # trains, collects, drives or runs an app (pytest -m "not slow" skips it)

PLUGIN_DIST = "cicfw-attention-mixer"
INSTALL = "pip install ./plugins/cicfw-attention-mixer"


@pytest.fixture(scope="module")
def plugin_installed() -> None:
    if "attention" not in MIXERS:
        pytest.fail(f"the example plugin is not installed in this environment; run `{INSTALL}`")


def test_example_plugin_is_registered_with_its_distribution(plugin_installed):
    assert MIXERS.origin("attention") == PLUGIN_DIST
    assert MIXERS.origin("gtu") == "cicfw"
    rows = {(kind, name): (dist, config) for kind, name, dist, _, config in listing()[0]}
    assert rows[("mixers", "attention")] == (f"{PLUGIN_DIST} 0.1.0", "mixer=attention")
    assert rows[("heads", "hybrid")][0].startswith("cicfw ")


def test_fast_dev_run_trains_with_the_plugin_mixer_by_name(plugin_installed, tiny_data, tmp_path):
    cfg = compose_train(
        "mixer=attention", "mixer.hidden=64", "head=hybrid", "data=cil_hdf5", f"data.path={tiny_data}",
        "data.batch_size=8", "data.val_batch_size=8", "debug=fast", "progress_bar=false",
    )
    assert cfg.mixer.name == "attention" and cfg.mixer.heads == 4  # the plugin's own yaml, via its SearchPathPlugin
    value = train(cfg, tmp_path / "run")
    assert 0.0 <= value < 2.0


def test_a_plugin_refusing_its_settings_is_one_line_and_leaves_no_run(plugin_installed, tiny_data, tmp_path):
    """The contract lets a plugin refuse bad kwargs with a plain ValueError: a user error, not a traceback."""
    run = tmp_path / "run"
    result = run_app_in_process("cicfw.train", "mixer=attention", "mixer.heads=3", "data=cil_hdf5",
                                f"data.path={tiny_data}", f"hydra.run.dir={run}")
    assert_refused(result, "mixer.heads", 3)
    assert not run.exists()


def _fake_dist(site: Path, name: str, entry_points: str, module: str, source: str) -> None:
    """An installed distribution as pip leaves it: a dist-info folder with entry_points.txt."""
    info = site / f"{name.replace('-', '_')}-1.0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(textwrap.dedent(entry_points))
    (site / f"{module}.py").write_text(textwrap.dedent(source))


@pytest.fixture
def broken_plugins(tmp_path: Path) -> Path:
    """Two bad plugins: one whose module raises on import, one that takes the built-in name 'gtu'."""
    site = tmp_path / "site"
    _fake_dist(site, "broken-mixer", "[cicfw.mixers]\nbroken = broken_mixer:BrokenMixer\n",
               "broken_mixer", "raise ImportError('needs libfoo, which is not installed')\n")
    _fake_dist(site, "clashing-mixer", "[cicfw.mixers]\ngtu = clashing_mixer:OtherGTU\n",
               "clashing_mixer", "from cicfw.model.mixers import Mixer\nclass OtherGTU(Mixer):\n    pass\n")
    return site


def test_broken_plugins_warn_by_name_and_builtins_still_work(broken_plugins, monkeypatch):
    from cicfw.model.mixers.gtu import GTUMixer

    monkeypatch.syspath_prepend(str(broken_plugins))
    # A fresh discovery pass over the real MIXERS registry (state restored after the test).
    monkeypatch.setattr(MIXERS, "_loaded", False)
    monkeypatch.setattr(MIXERS, "_entries", dict(MIXERS._entries))
    monkeypatch.setattr(MIXERS, "_origin", dict(MIXERS._origin))
    monkeypatch.setattr(MIXERS, "failed", {})
    with pytest.warns(UserWarning) as caught:
        names = MIXERS.names()
    messages = "\n".join(str(w.message) for w in caught)
    assert "'broken' from distribution 'broken-mixer'" in messages and "needs libfoo" in messages
    assert "'gtu' from distribution 'clashing-mixer'" in messages and "already registered by 'cicfw'" in messages
    assert "broken" not in names and MIXERS.get("gtu") is GTUMixer and MIXERS.origin("gtu") == "cicfw"
    assert set(MIXERS.failed) == {"broken-mixer:broken", "clashing-mixer:gtu"}
    assert main([]) == 0 and main(["--strict"]) == 1  # `cicfw plugins --strict` fails CI on a broken plugin


def test_cicfw_plugins_lists_everything_and_the_failures(plugin_installed, broken_plugins):
    env = {**os.environ, "PYTHONPATH": str(broken_plugins), "COLUMNS": "250"}
    run = subprocess.run([sys.executable, "-m", "cicfw.registry"], env=env, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    out = run.stdout
    lines = {line.split("│")[2].strip(): line for line in out.splitlines() if line.count("│") == 6}
    assert PLUGIN_DIST in lines["attention"] and "mixer=attention" in lines["attention"]
    ours = f"cicfw {version('cicfw')}"  # the installed distribution's version, whatever it is
    assert ours in lines["gtu"] and ours in lines["cil"] and ours in lines["regression"]
    failed = out[out.index("failed to load"):]
    assert "broken-mixer:broken" in failed and "needs libfoo" in failed
    assert "clashing-mixer:gtu" in failed and "already registered" in failed


class _WrongShape(Mixer):
    def __init__(self, in_dim: int, out_dim: int) -> None:
        super().__init__(in_dim, out_dim)
        self.lin = torch.nn.Linear(in_dim, out_dim)

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        return self.lin(h)  # (B, K): forgot the branches


class _UnusedParameter(_WrongShape):
    def __init__(self, in_dim: int, out_dim: int) -> None:
        super().__init__(in_dim, out_dim)
        self.spare = torch.nn.Linear(3, 3)

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        return self.lin(h).unsqueeze(1).expand(-1, 4, -1)


class _MixesSamples(_UnusedParameter):
    def forward(self, h: torch.Tensor) -> torch.Tensor:
        return (self.lin(h) + self.spare(h[:, :3]).sum() + h.mean()).unsqueeze(1).expand(-1, 4, -1)


@pytest.mark.parametrize("cls, complaint", [
    (_WrongShape, "expected (5, 4, 1)"),
    (_UnusedParameter, "without a gradient"),
    (_MixesSamples, "depends on the rest of the batch"),
])
def test_contract_checks_catch_a_broken_mixer(cls, complaint, monkeypatch):
    monkeypatch.setitem(MIXERS._entries, "bad", cls)
    with pytest.raises(AssertionError, match=complaint.replace("(", r"\(").replace(")", r"\)")):
        check_mixer("bad")


def test_contract_checks_pass_for_every_registered_part():
    for name in MIXERS.names():
        check_mixer(name)
    from cicfw.registry import HEADS

    for name in HEADS.names():
        check_head(name)


def test_write_tiny_dataset_never_writes_over_a_file(tmp_path):
    """CoRL-2017's files are named as the tiny ones (data_00000.h5 ...): a real folder given by mistake keeps
    its images."""
    from cicfw.core.errors import CicfwError
    from cicfw.testing import write_tiny_dataset

    real = tmp_path / "SeqVal"
    real.mkdir()
    (real / "data_00001.h5").write_bytes(b"a recorded episode")
    with pytest.raises(CicfwError) as err:
        write_tiny_dataset(real, n_files=2, n=4)
    assert (err.value.key, err.value.value) == ("folder", str(real))
    assert sorted(p.name for p in real.iterdir()) == ["data_00001.h5"]  # nothing written, before or after
    assert (real / "data_00001.h5").read_bytes() == b"a recorded episode"
    write_tiny_dataset(real, n_files=2, n=4, overwrite=True)
    assert sorted(p.name for p in real.iterdir()) == ["data_00000.h5", "data_00001.h5"]


@pytest.mark.parametrize("check, key, value", [("mixer", "batch", 0), ("mixer", "batch", 1), ("mixer", "in_dim", 0),
                                               ("head", "batch", 0)])
def test_the_contract_checks_refuse_a_size_that_checks_nothing(check, key, value):
    """check_mixer(batch=0) passed on an empty batch, checking nothing; check_head(batch=0) blamed the head's
    loss for the NaN of an empty mean."""
    from cicfw.core.errors import ConfigError
    from cicfw.testing import check_head, check_mixer

    with pytest.raises(ConfigError) as err:
        (check_mixer if check == "mixer" else check_head)("independent" if check == "mixer" else "softmax",
                                                           **{key: value})
    assert (err.value.key, err.value.value) == (key, value)


# ---- a --config-dir file named like a built-in config: refused, naming the file and the config that wins
SHADOWED = [
    ("cicfw.train", "mixer/gtu.yaml", "pkg://cicfw.conf/mixer/gtu.yaml", ["mixer=gtu"]),
    ("cicfw.train", "train.yaml", "pkg://cicfw.conf/train.yaml", []),
    ("cicfw.train", "mixer/attention.yaml", "pkg://cicfw_attention_mixer.conf/mixer/attention.yaml",
     ["mixer=attention"]),
    ("cicfw.evaluate", "suite/junctions.yaml", "pkg://cicfw.conf/suite/junctions.yaml", []),
    ("cicfw.export", "hydra/job_logging/default.yaml", "pkg://hydra.conf/hydra/job_logging/default.yaml", []),
]


@pytest.mark.parametrize("app, name, winner, args", SHADOWED, ids=[f"{app}:{name}" for app, name, _, _ in SHADOWED])
def test_a_config_dir_file_a_builtin_would_hide_is_refused(plugin_installed, tmp_path, app, name, winner, args):
    """Hydra reads the --config-dir folder after the app's configs and the plugins', so such a file was ignored
    and the run composed the built-in (mixer=gtu trained hidden: 256, not the file's 64) without a word."""
    (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
    (tmp_path / name).write_text("name: independent\nhidden: 64\n")
    result = run_app_in_process(app, "--config-dir", str(tmp_path), *args, "--cfg", "job")
    assert_refused(result, tmp_path / name, winner)
    assert result.stdout == ""  # nothing composed


def test_a_config_dir_option_of_its_own_name_is_composed(tmp_path):
    """A new name in the --config-dir folder is the user's option; a folder that is no config group is not read."""
    (tmp_path / "mixer").mkdir()
    (tmp_path / "mixer" / "mine.yaml").write_text("name: independent\nhidden: 64\n")
    (tmp_path / "notes" / "mixer").mkdir(parents=True)
    (tmp_path / "notes" / "mixer" / "gtu.yaml").write_text("hidden: 1\n")
    result = run_app_in_process("cicfw.train", "--config-dir", str(tmp_path), "mixer=mine", "--cfg", "job")
    assert result.returncode == 0, result.stderr[-3000:]
    assert yaml.safe_load(result.stdout)["mixer"] == {"name": "independent", "hidden": 64}
