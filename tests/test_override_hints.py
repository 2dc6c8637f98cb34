"""A mistyped override key gets Hydra's message plus the keys that exist; a bad group option is
left to Hydra, which lists the group's options itself."""
from __future__ import annotations

import sys

import pytest

from cicfw.override_hints import override_hints, run_app

pytestmark = pytest.mark.slow  # trains, collects, drives or runs an app (pytest -m "not slow" skips it)


def test_top_level_typo_suggests_the_key_and_lists_keys_and_groups():
    (hint,) = override_hints("train", ["trainr.max_epochs=1"])
    assert "no key 'trainr'; did you mean 'trainer'?" in hint
    assert "keys there:" in hint and " seed" in hint and "launcher" in hint and "hydra," not in hint


def test_the_groups_listed_are_the_apps_own():
    """evaluate's hint names its groups (policy, sim, suite), not train's (mixer, head) it cannot take."""
    (hint,) = override_hints("evaluate", ["suitee=single_turn"])
    groups = hint.split("config groups there (choose with group=option): ")[1]
    assert groups.split(", ") == ["policy", "sim", "suite"]
    assert "did you mean 'suite'" in hint
    (hint,) = override_hints("train", ["mixr=gtu"])
    assert {"mixer", "head", "experiment", "launcher"} <= set(hint.split("group=option): ")[1].split(", "))
    assert "budget" not in hint and "policy" not in hint


def test_nested_typo_in_the_chosen_group_option():
    (hint,) = override_hints("train", ["head=hybrid", "head.WW=5"])
    assert "'head' has no key 'WW'; did you mean 'W'?" in hint and "bin_width" in hint


def test_valid_overrides_and_group_choices_give_no_hint():
    assert override_hints("train", ["-m", "mixer=gtu,re", "head=hybrid", "head.W=5,10", "+extra=1", "hydra.job.chdir=false"]) == []
    assert override_hints("train", ["mixer=gtuu"]) == []  # Hydra's own message lists the options


def test_run_app_prints_hints_only_on_failure(monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["cicfw.train", "data.batchsize=3"])

    def failing_app() -> None:
        sys.exit(1)

    with pytest.raises(SystemExit):
        run_app(failing_app, "train")
    assert "did you mean 'batch_size'" in capsys.readouterr().err
    run_app(lambda: None, "train")
    assert capsys.readouterr().err == ""


def test_an_option_whose_plugin_is_missing_names_the_extra(monkeypatch):
    import importlib.util

    from cicfw import override_hints as hints_module

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name.startswith("hydra_plugins.hydra_optuna") else real(name, *a))
    (hint,) = hints_module.missing_extras(["hparams_search=optuna", "launcher=joblib", "mixer=gtu"])
    assert "hparams_search=optuna needs the 'sweeps' extra" in hint and 'cicfw[sweeps]' in hint


def test_mandatory_values_count_as_present():
    assert override_hints("train", ["data=cil_hdf5", "data.path=/x", "data.batch_size=8"]) == []


@pytest.mark.parametrize("app", ["evaluate", "diagnose", "export", "collect"])
def test_every_hydra_app_hints_at_a_mistyped_top_level_key(app):
    """Not only train: ``cicfw diagnose progress_bar=false`` used to end on Hydra's message alone."""
    import subprocess

    r = subprocess.run([sys.executable, "-m", f"cicfw.{app}", "bogus_keyy=1"], capture_output=True, text=True,
                       timeout=300, cwd="/")
    assert r.returncode != 0
    assert "cicfw: hint: the top level of the config has no key 'bogus_keyy'" in r.stderr, r.stderr[-800:]


def test_the_collect_experts_documented_keys_need_no_plus_and_a_typo_lists_them():
    """``cicfw collect expert.cruise_kmh=30`` as conf/collect.yaml documents it; ``expert.cruise=30``
    names the ExpertParams keys there."""
    assert override_hints("collect", ["expert.cruise_kmh=30"]) == []
    (hint,) = override_hints("collect", ["expert.cruise=30"])
    assert "'expert' has no key 'cruise'; did you mean 'cruise_kmh'?" in hint
    assert "keys there: cruise_kmh, decel, lateral_accel, lookahead_base" in hint


def test_a_key_under_an_empty_node_is_told_to_take_a_plus():
    """``data.collect: {}`` takes the collector's keys, added with ``+``: the hint says so, not "has no key"."""
    (hint,) = override_hints("train", ["data.collect.towns=[town_b]"])
    assert hint == ("cicfw: hint: 'data.collect' is empty in the config (the keys it takes are documented beside "
                    "it), so a key under it is added with '+': +data.collect.towns=[town_b]")
    assert override_hints("train", ["+data.collect.towns=[town_b]"]) == []


@pytest.mark.parametrize("code", [130, 143])
def test_an_interrupted_app_gets_no_hints(monkeypatch, capsys, code):
    """Ctrl-C (130) and SIGTERM (143) are stops, not config mistakes: no second composition, no hint."""
    monkeypatch.setattr(sys, "argv", ["cicfw.train", "data.batchsize=3"])

    def stopped_app() -> None:
        sys.exit(code)

    with pytest.raises(SystemExit):
        run_app(stopped_app, "train")
    assert capsys.readouterr().err == ""
