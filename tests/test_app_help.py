"""Each app's ``--help`` lists the config groups that app reads (its defaults list and what its options'
defaults lists reach), not the other apps' groups nor the schemas' plumbing (``cicfw_schema/...``).

The train app's ``--help`` runs as ``python -m cicfw.train --help`` in a process of its own (a fork of an
interpreter that has imported torch and Lightning), as a user's shell starts it: Hydra renders the help
template with the groups the app reads. The other apps' ``--help`` run in this process, each from its entry
point with the template's resolver unregistered first."""
from __future__ import annotations

import pytest

from cicfw.core.override_hints import HELP_RESOLVER
from conftest import run_app_in_process, run_apps_forked

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


@pytest.mark.parametrize("config_name", [name for name in GROUPS if name != "train"])
def test_every_app_s_help_lists_the_groups_that_app_reads(config_name, tmp_path, monkeypatch):
    """The app's own ``--help``, in this process: its entry point registers the template's resolver (which the
    train app's registered here would hide)."""
    from omegaconf.basecontainer import BaseContainer

    monkeypatch.delitem(BaseContainer._resolvers, HELP_RESOLVER, raising=False)
    run = run_app_in_process(f"cicfw.{config_name}", "--help", cwd=tmp_path)
    assert run.returncode == 0, run.stderr[-2000:]
    listing = run.stdout.split("== Configuration groups ==", 1)[1].split("== Config ==", 1)[0]
    assert offered(listing) == GROUPS[config_name], listing
    assert "cicfw_schema" not in listing and list(tmp_path.iterdir()) == []


def test_an_app_s_help_skips_the_listings_it_does_not_print_and_hydra_help_keeps_them(tmp_path, monkeypatch):
    """Hydra lists every group of the tree twice for any ``--help`` (most of its seconds); the app's template
    prints neither listing, so they are skipped there, and ``--hydra-help``, which prints them, keeps them."""
    from hydra._internal.hydra import Hydra
    from omegaconf.basecontainer import BaseContainer

    listed = []
    original = Hydra.format_config_groups
    monkeypatch.setattr(Hydra, "format_config_groups", lambda self, *a, **k: listed.append(1) or original(self, *a, **k))
    monkeypatch.delitem(BaseContainer._resolvers, HELP_RESOLVER, raising=False)
    run = run_app_in_process("cicfw.collect", "--help", cwd=tmp_path)
    assert run.returncode == 0 and "sim: " in run.stdout and listed == [], (run.stderr[-2000:], listed)
    run = run_app_in_process("cicfw.collect", "--hydra-help", cwd=tmp_path)
    assert run.returncode == 0 and "hydra/launcher: " in run.stdout and listed, run.stderr[-2000:]
    assert list(tmp_path.iterdir()) == []
