"""Each app's ``--help`` lists the config groups that app reads (its defaults list and what its options'
defaults lists reach), not the other apps' groups nor the schemas' plumbing (``cicfw_schema/...``).

Each app runs as ``python -m <app> --help`` in a process of its own, as a user's shell starts it, so that
Hydra's config store holds that app's schemas only. The six processes are forked from one interpreter that
has imported the third-party libraries every app imports first (torch, Lightning): each fork skips those
imports (most of an app's start), and imports cicfw and its app itself, as a fresh process does."""
from __future__ import annotations

import pytest

from conftest import AppResult, run_apps_forked

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

@pytest.fixture(scope="module")
def helps(tmp_path_factory) -> dict[str, AppResult]:
    """Every app's ``--help``, each from its own process (a fork of one interpreter started here)."""
    return run_apps_forked({m: [m, "--help"] for m in GROUPS}, cwd=tmp_path_factory.mktemp("help"))


@pytest.mark.parametrize("module", GROUPS)
def test_help_lists_the_groups_the_app_reads(module, helps):
    run = helps[module]
    assert run.returncode == 0, run.stderr[-2000:]
    section = run.stdout.split("== Configuration groups ==", 1)[1].split("== Config ==", 1)[0]
    offered = {line.split(":", 1)[0] for line in section.splitlines()[1:] if ": " in line and not line.startswith("(")}
    assert offered == GROUPS[module], section
    assert "cicfw_schema" not in run.stdout
    if module == "cicfw.train":  # the options too, a plugin's included where one is installed
        assert any(line.startswith("mixer: ") and "gtu" in line for line in section.splitlines()), section
