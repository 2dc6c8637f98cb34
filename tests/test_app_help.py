"""Each app's ``--help`` lists the config groups that app reads (its defaults list and what its options'
defaults lists reach), not the other apps' groups nor the schemas' plumbing (``cicfw_schema/...``).

The train app's ``--help`` runs as ``python -m cicfw.train --help`` in a process of its own (a fork of an
interpreter that has imported torch and Lightning), as a user's shell starts it: Hydra renders the help
template with the groups the app reads. The other apps share that template (``override hydra/help: cicfw``
in each app config, checked here by composing it) and their groups come from the same function
(``app_groups``), called here for each app config: Hydra's own ``--help`` costs seconds an app in listing
every group of the tree, which the template does not print."""
from __future__ import annotations

import pytest
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

from cicfw.core.override_hints import HELP_RESOLVER, app_groups
from conftest import run_apps_forked

#: app config -> the groups its --help offers
GROUPS = {
    "train": {"data", "debug", "encoder", "experiment", "head", "hparams_search", "launcher", "logger", "mixer",
              "speed", "trainer"},
    "evaluate": {"policy", "sim", "suite"},
    "collect": {"sim"},
    "export": set(),
    "diagnose": set(),
    "reproduce": {"budget", "launcher"},
}


def offered(section: str) -> set[str]:
    """The group names of a ``group: option, option`` listing."""
    return {line.split(":", 1)[0] for line in section.splitlines() if ": " in line and not line.startswith("(")}


@pytest.mark.slow  # starts the app
def test_the_train_app_s_help_lists_the_groups_it_reads_and_their_options(tmp_path):
    run = run_apps_forked({"train": ["cicfw.train", "--help"]}, cwd=tmp_path)["train"]
    assert run.returncode == 0, run.stderr[-2000:]
    section = run.stdout.split("== Configuration groups ==", 1)[1].split("== Config ==", 1)[0]
    assert offered(section) == GROUPS["train"], section
    assert "cicfw_schema" not in run.stdout
    assert any(line.startswith("mixer: ") and "gtu" in line for line in section.splitlines()), section  # a plugin's too


@pytest.mark.parametrize("config_name", GROUPS)
def test_every_app_s_help_lists_the_groups_that_app_reads(config_name):
    with initialize_config_module("cicfw.conf", version_base="1.3"):
        cfg = compose(config_name, return_hydra_config=True)
        listing = app_groups(config_name)
    template = OmegaConf.to_container(cfg.hydra.help)["template"]
    assert "${" + HELP_RESOLVER + ":${hydra.job.config_name}}" in template  # the cicfw help, not Hydra's
    assert offered(listing) == GROUPS[config_name], listing
    assert "cicfw_schema" not in listing
