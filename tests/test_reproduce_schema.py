"""The reproduce config is checked by its schema (cicfw/reproduction/schema.py), its nodes' keys taken from the code
that reads them: OmegaConf refuses a wrong type or an unknown key while composing, naming its full key; what
composing lets through (keys added with ``+``, ``seeds``, ``weather_family``, catalogue rows and claims) is
refused by the same schema before anything is written, collected or trained. Each test asserts the
refusal's kind and the key it names, not its sentence."""
from __future__ import annotations

import dataclasses
import inspect
from importlib.resources import files
from pathlib import Path

import pytest
import yaml
from hydra import compose, initialize_config_module
from hydra.errors import HydraException

from cicfw.core.config_checks import SchemaError, config_error
from cicfw.core.errors import ConfigError
from cicfw.reproduction.schema import BudgetConfig, check
from cicfw.reproduction import app as reproduce

CONF = Path(str(files("cicfw.conf")))
BUDGETS = sorted(p.stem for p in (CONF / "budget").glob("*.yaml"))


def compose_reproduce(*overrides: str):
    with initialize_config_module("cicfw.conf", version_base="1.3"):
        return compose("reproduce", overrides=list(overrides))


def refused(*overrides: str) -> SchemaError:
    """The refusal of ``overrides``: OmegaConf's while composing, else ``check``'s."""
    try:
        cfg = compose_reproduce(*overrides)
    except HydraException as err:
        got = config_error(err)
        assert got is not None, err
        return got
    with pytest.raises(SchemaError) as err:
        check(cfg)
    assert "\n" not in str(err.value)
    return err.value


#: what an audit found accepted at plan time, or failing unclearly
AUDIT = [
    (["progress_bar=perhaps"], "wrong type", "progress_bar"),
    (["+cell.foo=1"], "unknown key", "cell.foo"),
    (["weather_family=3"], "wrong type", "weather_family"),
    (["budget.suite=abc"], "wrong type", "budget.suite"),
    (["results_dir=[1]"], "wrong type", "results_dir"),
    (["publish_dir=[1]"], "wrong type", "publish_dir"),
    (["claims=abc"], "wrong type", "claims"),
    (["budget.train=abc"], "wrong type", "budget.train"),
]


#: what the refusal of an override of the list below says it accepts
SAYS = {"seeds=abc": ["a list of distinct seeds"], "weather_family=3": ["carla", "harsh"],
        "relation_candidates=[re_all,re_pears]": ["'re_pears', not a catalogue row"]}


@pytest.mark.parametrize("overrides, kind, key", [
    *AUDIT,
    (["seeds=abc"], "wrong type", "seeds"),
    (["seeds=[1,x]"], "wrong type", "seeds"),
    (["rows=cil"], "wrong type", "rows"),
    (["continue_from=[1]"], "wrong type", "continue_from"),
    (["equivalence_margin=abc"], "wrong type", "equivalence_margin"),
    (["relation_candidates=abc"], "wrong type", "relation_candidates"),
    (["relation_candidates=[re_all,re_pears]"], "wrong type", "relation_candidates"),
    (["budget.name=[1]"], "wrong type", "budget.name"),
    (["budget.curve_epochs=[abc]"], "wrong type", "budget.curve_epochs[0]"),
    (["+budget.foo=1"], "unknown key", "budget.foo"),
    (["cell.seed=abc"], "wrong type", "cell.seed"),
    (["+foo=1"], "unknown key", "foo"),
    (["weather_familly=harsh"], "unknown key", "weather_familly"),
    (["catalogue=abc"], "wrong type", "catalogue"),
    (["+catalogue.mine=abc"], "wrong type", "catalogue.mine"),
    (["+catalogue.mine={experiment: paper_gtu, labl: x}"], "unknown key", "catalogue.mine.labl"),
    (["+catalogue.mine={label: x}"], "missing", "catalogue.mine.experiment"),
    (["+catalogue.mine={experiment: paper_gtu, label: x, overrides: abc}"], "wrong type", "catalogue.mine.overrides"),
    (["catalogue.cil.paper=[1,x,3,4]"], "wrong type", "catalogue.cil.paper[1]"),
    (["claims=[abc]"], "wrong type", "claims[0]"),
    (["claims=[{id: x, claim: y, parts: abc}]"], "wrong type", "claims[0].parts"),
    (["claims=[{id: x, parts: [{a: gtu, b: cil}]}]"], "missing", "claims[0].claim"),
    (["claims=[{id: x, claim: y, famly: w, parts: [{a: gtu, b: cil}]}]"], "unknown key", "claims[0].famly"),
    (["claims=[{id: x, claim: y, parts: [{a: gtu, b: cil}, {a: gtu, b: cil, on: overall}]}]"], "unknown key",
     "claims[0].parts[1].on"),
    (["claims=[{id: x, claim: y, parts: [{a: gtu, b: cil, relative: perhaps}]}]"], "wrong type",
     "claims[0].parts[0].relative"),
])
def test_the_schema_refuses_naming_the_full_key(overrides, kind, key):
    got = refused(*overrides)
    assert (got.kind, got.key) == (kind, key), got
    for text in SAYS.get(overrides[0], ()):  # and what it accepts, where the line says so
        assert text in str(got), got


@pytest.mark.parametrize("overrides, key, value", [
    (["catalogue.cil.paper=[1,2,3]"], "catalogue.cil.paper", [1, 2, 3]),
    (["budget.curve_epochs=[0]"], "budget.curve_epochs", [0]),
    (["budget.curve_seeds=[2,-1]"], "budget.curve_seeds", [2, -1]),
    (["equivalence_margin=0"], "equivalence_margin", 0),
])
def test_the_check_refuses_a_value_out_of_range_naming_key_and_value(overrides, key, value):
    with pytest.raises(ConfigError) as err:
        check(compose_reproduce(*overrides))
    assert (err.value.key, err.value.value) == (key, value), err.value


def test_an_unknown_key_says_the_key_it_is_close_to():
    assert "'publish_dir'" in str(refused("publish_dirr=x"))  # did you mean


@pytest.mark.parametrize("budget", BUDGETS)
def test_every_budget_and_the_docs_row_pass_the_check(budget):
    check(compose_reproduce(f"budget={budget}", "weather_family=harsh", "seeds=[3,4]",
                            '+catalogue.mine={experiment: paper_gtu, overrides: ["head=hybrid"], label: GTU+hybrid}'))


def test_the_nodes_take_their_keys_from_the_code():
    """A row's keys are ``Row``'s, a claim's and a part's the arguments of the functions that load them, a
    budget's every key conf/budget/*.yaml holds, the top level conf/reproduce.yaml's and its budget group."""
    from cicfw.reproduction.schema import CLAIM, PART, ROW, ReproduceConfig
    from cicfw.reproduction.catalogue import Row
    from cicfw.reproduction.claims import claim_entry, claim_part

    fields = lambda schema: {f.name for f in dataclasses.fields(schema)}  # noqa: E731
    assert fields(ROW) == fields(Row) == {"experiment", "overrides", "label", "paper"}
    assert fields(CLAIM) == set(inspect.signature(claim_entry).parameters)
    assert fields(PART) == set(inspect.signature(claim_part).parameters)
    held = set().union(*(yaml.safe_load((CONF / "budget" / f"{b}.yaml").read_text()) for b in BUDGETS))
    assert fields(BudgetConfig) == held
    shipped = yaml.safe_load((CONF / "reproduce.yaml").read_text())
    assert fields(ReproduceConfig) == set(shipped) - {"defaults", "hydra"} | {"budget"}
    cfg = compose_reproduce()
    assert all(set(entry) <= fields(Row) for entry in cfg.catalogue.values())


class Collected(Exception):
    """Raised where the app would collect the budget's dataset or train a cell."""


@pytest.mark.slow
@pytest.mark.parametrize("overrides, kind, key", AUDIT)
def test_the_app_refuses_in_one_line_writing_collecting_and_training_nothing(overrides, kind, key, tmp_path, capsys,
                                                                            monkeypatch):
    import cicfw.train.app

    def work(*args, **kwargs):
        raise Collected("the app went on to collect or train")

    monkeypatch.setattr(cicfw.train.app, "ensure_data", work)
    monkeypatch.setattr(reproduce, "ensure_data", work)  # the app imported it by name
    monkeypatch.setattr(cicfw.train.app, "train", work)
    monkeypatch.setattr(reproduce, "train", work)  # the app imported it by name
    out = tmp_path / "results"
    args = ["budget=smoke", "rows=[cil]", "seeds=1", *overrides]
    args += [] if any(o.startswith("results_dir=") for o in overrides) else [f"results_dir={out}"]
    assert reproduce.main(args) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith(f"cicfw: error: {key} ") or f"{key}'" in line, line
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_checking_a_plan_composes_each_cells_training_config_once(monkeypatch):
    """While a plan is checked, a cell's training config is composed once and each caller gets its own
    copy; outside that, as when a cell trains, every call composes afresh."""
    from omegaconf import OmegaConf

    composed = []
    real = reproduce.compose
    monkeypatch.setattr(reproduce, "compose", lambda name, overrides: composed.append(name) or real(name, overrides=overrides))
    cfg = compose_reproduce("budget=smoke", "rows=[cil,gtu]", "seeds=2")
    with initialize_config_module("cicfw.conf", version_base="1.3"):
        fresh = OmegaConf.to_container(reproduce.compose_train(cfg, "cil", 0))
        with reproduce.checking_the_plan():
            first = reproduce.compose_train(cfg, "cil", 0)
            first.model.lr = 123.0  # a caller's change stays in its copy
            again = reproduce.compose_train(cfg, "cil", 0)
            other = reproduce.compose_train(cfg, "gtu", 1)
        after = reproduce.compose_train(cfg, "cil", 0)
    assert composed == ["train"] * 4  # fresh, cil/0 once, gtu/1, after
    assert OmegaConf.to_container(again) == fresh == OmegaConf.to_container(after)
    assert other.seed == 1 and other.mixer.name != again.mixer.name
