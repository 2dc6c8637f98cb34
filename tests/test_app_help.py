"""Each app's ``--help`` lists the config groups that app reads (its defaults list and what its options'
defaults lists reach), not the other apps' groups nor the schemas' plumbing (``cicfw_schema/...``)."""
from __future__ import annotations

import subprocess
import sys

import pytest

pytestmark = pytest.mark.slow  # starts the apps

#: module -> the groups its --help offers
GROUPS = {
    "cicfw.train": {"data", "debug", "encoder", "experiment", "head", "hparams_search", "launcher", "logger", "mixer",
                    "speed", "trainer"},
    "cicfw.evaluate": {"policy", "sim", "suite"},
    "cicfw.collect": {"sim"},
    "cicfw.export": set(),
    "cicfw.diagnose": set(),
    "cicfw.reproduce": {"budget", "launcher"},
}


@pytest.mark.parametrize("module", GROUPS)
def test_help_lists_the_groups_the_app_reads(module, tmp_path):
    run = subprocess.run([sys.executable, "-m", module, "--help"], capture_output=True, text=True, timeout=300,
                         cwd=tmp_path)
    assert run.returncode == 0, run.stderr[-2000:]
    section = run.stdout.split("== Configuration groups ==", 1)[1].split("== Config ==", 1)[0]
    offered = {line.split(":", 1)[0] for line in section.splitlines()[1:] if ": " in line and not line.startswith("(")}
    assert offered == GROUPS[module], section
    assert "cicfw_schema" not in run.stdout
    if module == "cicfw.train":  # the options too, a plugin's included where one is installed
        assert any(line.startswith("mixer: ") and "gtu" in line for line in section.splitlines()), section
