"""A plugin that cannot even be imported never stops a cicfw app, and
``cicfw plugins --json`` lists the registry for scripts.

The broken plugin is a fake installed distribution (a dist-info folder with RECORD and
entry_points.txt) on PYTHONPATH, laid out as docs/plugins.md tells plugin authors: a package, a
``hydra_plugins/<name>`` SearchPathPlugin that imports it, and a ``cicfw.mixers`` entry point."""
from __future__ import annotations

from importlib.metadata import version

import json
import os
import sys
import warnings
from pathlib import Path

import pytest

from cicfw.registry import MIXERS, as_json, listing, main
from conftest import AppResult, run_apps_forked

pytestmark = pytest.mark.slow  # trains, collects, drives or runs an app (pytest -m "not slow" skips it)

DIST = "broken-mixer"
SEARCH_PATH_PLUGIN = '''
from hydra.core.config_search_path import ConfigSearchPath
from hydra.plugins.search_path_plugin import SearchPathPlugin

import broken_mixer  # the plugin's own package: its top-level import fails


class BrokenMixerSearchPathPlugin(SearchPathPlugin):
    def manipulate_search_path(self, search_path: ConfigSearchPath) -> None:
        search_path.append(provider="broken-mixer", path="pkg://broken_mixer.conf")
'''


def _broken_site(tmp_path: Path, error: str = "RuntimeError('needs a GPU driver, none found')") -> Path:
    site = tmp_path / "site"
    (site / "broken_mixer").mkdir(parents=True)
    (site / "broken_mixer" / "__init__.py").write_text(f"raise {error}\n")
    (site / "hydra_plugins" / "broken_mixer").mkdir(parents=True)  # no hydra_plugins/__init__.py: a namespace
    (site / "hydra_plugins" / "broken_mixer" / "__init__.py").write_text(SEARCH_PATH_PLUGIN)
    info = site / "broken_mixer-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {DIST}\nVersion: 1.0\n")
    (info / "RECORD").write_text("broken_mixer/__init__.py,,\nhydra_plugins/broken_mixer/__init__.py,,\n"
                                 "broken_mixer-1.0.dist-info/METADATA,,\n")
    (info / "entry_points.txt").write_text("[cicfw.mixers]\nbroken = broken_mixer:BrokenMixer\n")
    return site




WARNING = (f"cicfw: skipped plugin distribution '{DIST}': its Hydra module 'hydra_plugins.broken_mixer' failed "
           f"to import (RuntimeError: needs a GPU driver, none found); its configs are not available, "
           f"everything else works")


APPS = {"train": ["cicfw.train"], "evaluate": ["cicfw.cli", "evaluate"]}


@pytest.fixture(scope="module")
def started(tmp_path_factory) -> dict[str, AppResult]:
    """Each app of APPS started (``--cfg job``) in a process of its own, the broken plugin installed (the
    processes are forks of one interpreter that has imported torch and Lightning: run_apps_forked)."""
    env = {**os.environ, "PYTHONPATH": str(_broken_site(tmp_path_factory.mktemp("apps"))), "HYDRA_FULL_ERROR": "0",
           "COLUMNS": "250"}
    return run_apps_forked({name: [*argv, "--cfg", "job"] for name, argv in APPS.items()}, env=env)


@pytest.mark.parametrize("app", APPS)
def test_an_app_starts_with_one_warning_naming_the_distribution(started, app):
    r = started[app]
    assert r.returncode == 0, r.stderr[-3000:]
    assert "Traceback" not in r.stderr
    assert r.stderr.count("cicfw: skipped") == 1 and WARNING in r.stderr, r.stderr
    assert "seed: 0" in r.stdout  # the composed config was printed: the app ran


@pytest.fixture
def fresh_scan(tmp_path, monkeypatch):
    """This process as if Hydra had not scanned its plugins yet, with the broken plugin installed."""
    from cicfw.core import hydra_plugins
    from hydra.core.plugins import Plugins
    from hydra.core.singleton import Singleton

    if Plugins in Singleton._instances:
        monkeypatch.delitem(Singleton._instances, Plugins)  # restored (Hydra's real scan) afterwards
    monkeypatch.setattr(hydra_plugins, "SKIPPED_HYDRA_MODULES", {})
    for attr, value in (("_loaded", False), ("_entries", dict(MIXERS._entries)),
                        ("_origin", dict(MIXERS._origin)), ("failed", {})):
        monkeypatch.setattr(MIXERS, attr, value)

    def install(error: str = "RuntimeError('needs a GPU driver, none found')") -> None:
        monkeypatch.syspath_prepend(str(_broken_site(tmp_path, error)))

    yield install
    for name in ("broken_mixer", "hydra_plugins.broken_mixer"):
        sys.modules.pop(name, None)


def _compose_train():
    from hydra import compose, initialize_config_module

    with initialize_config_module("cicfw.conf", version_base="1.3"):
        return compose("train", overrides=["mixer=gtu"])


def test_without_the_guard_the_broken_plugin_stops_hydra(fresh_scan):
    from hydra.core.plugins import Plugins

    fresh_scan()
    with pytest.raises(RuntimeError, match="needs a GPU driver"):
        Plugins.instance()  # what every Hydra app did before cicfw guarded the scan


def test_the_guard_skips_it_with_one_warning_and_hydra_works(fresh_scan):
    from cicfw.core.hydra_plugins import guard_hydra_plugins

    fresh_scan()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        skipped = guard_hydra_plugins()
        assert _compose_train().mixer.name == "gtu"  # Hydra scanned its plugins and composes
        names = MIXERS.names()  # the same distribution's entry point fails too: no second warning
    assert skipped == {"hydra_plugins.broken_mixer": (DIST, "RuntimeError: needs a GPU driver, none found")}
    assert [str(w.message) for w in caught if "cicfw:" in str(w.message)] == [WARNING]
    assert "gtu" in names and "broken" not in names and f"{DIST}:broken" in MIXERS.failed
    failed = {plugin: (kind, error) for kind, plugin, error in listing()[1]}
    assert failed[f"{DIST}:hydra_plugins.broken_mixer"] == ("hydra modules", "RuntimeError: needs a GPU driver, none found")
    assert guard_hydra_plugins() == {}  # once Hydra has scanned, later calls do nothing


def test_an_import_error_also_gets_the_one_warning_instead_of_hydras(fresh_scan):
    from cicfw.core.hydra_plugins import guard_hydra_plugins

    fresh_scan("ImportError('needs libfoo')")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        guard_hydra_plugins()
        _compose_train()
    messages = [str(w.message) for w in caught]
    ours = [m for m in messages if m.startswith("cicfw: skipped")]
    assert len(ours) == 1 and f"'{DIST}'" in ours[0] and "ImportError: needs libfoo" in ours[0]
    assert not [m for m in messages if "Plugin is incompatible with this Hydra version" in m]  # Hydra's own


def test_plugins_json_lists_every_entry_and_failure(tmp_path, monkeypatch, capsys):
    site = tmp_path / "site"
    info = site / "failing_mixer-1.0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: failing-mixer\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text("[cicfw.mixers]\nfailing = failing_mixer:M\n")
    (site / "failing_mixer.py").write_text("raise ImportError('needs libfoo')\n")
    monkeypatch.syspath_prepend(str(site))
    for attr, value in (("_loaded", False), ("_entries", dict(MIXERS._entries)),
                        ("_origin", dict(MIXERS._origin)), ("failed", {})):
        monkeypatch.setattr(MIXERS, attr, value)
    with pytest.warns(UserWarning, match="failing-mixer"):
        MIXERS.names()
    assert main(["--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    rows = {(r["kind"], r["name"]): r for r in data["registered"]}
    assert rows[("mixers", "gtu")] == {"kind": "mixers", "name": "gtu", "distribution": "cicfw", "version": version("cicfw"),
                                      "class": "cicfw.model.mixers.gtu.GTUMixer", "config": "mixer=gtu"}
    assert {(r["kind"], r["name"]) for r in data["registered"]} == {(k, n) for k, n, *_ in listing()[0]}
    assert data["failed"] == [{"kind": "mixers", "plugin": "failing-mixer:failing", "error": "ImportError: needs libfoo"}]
    assert main(["--json", "--strict"]) == 1
    assert json.loads(as_json([("mixers", "x", "d 1.0", "m.X", "-")], []))["registered"][0]["config"] is None
