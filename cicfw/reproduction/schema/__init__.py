"""The reproduce app's config schema, taken from the code that reads each node, and registered with Hydra.

conf/reproduce.yaml puts this package on its search path (cicfw.reproduction.app imports it too), so Hydra
imports it (registering ``cicfw_reproduce`` in its ConfigStore) before it composes a reproduce config, and
the defaults list lays it under the config first, so OmegaConf refuses an unknown key or a value of the wrong
type while composing, naming its full key. ``check`` looks at a composed config only for what composing lets
through, once: keys added with ``+``, ``seeds`` (a number or a list, a union OmegaConf cannot type),
``weather_family`` (one of the simulator's families), and each catalogue row and claim: a row takes
``cicfw.reproduction.catalogue.Row``'s keys, a claim and its parts ``claim_entry``'s and ``claim_part``'s
arguments (cicfw/reproduction/claims.py). Those two nodes stay open while composing: OmegaConf cannot add a
row to a typed mapping (``+catalogue.mine={...}``), and names no list item's full key. The app runs ``check``
on its plan (``compose_plan``) before anything is written; the cells run that plan.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, DictConfig, OmegaConf

from cicfw.core.config_checks import (SEED_RANGE, SchemaError, check_composed, checked, is_integer, kwargs_schema,
                                      plain_values)
from cicfw.core.errors import ConfigError
from cicfw.reproduction.catalogue import PAPER_VALUES, Row
from cicfw.reproduction.claims import check_margin, claim_entry, claim_part
from cicfw.sim.render.weather import WEATHER_FAMILIES

ROW = kwargs_schema(Row, "a catalogue row", is_not="a key of a catalogue row")
PART = kwargs_schema(claim_part, "a claim's part", is_not="a key of a claim's part")
CLAIM = kwargs_schema(claim_entry, "a claim", is_not="a key of a claim", fields={"parts": (List[Any], MISSING)})


@dataclass
class BudgetConfig:
    """conf/budget/<name>.yaml: what every cell of a results folder trains on and drives."""

    __cicfw_is_not__ = "a key of a budget (conf/budget/<name>.yaml)"

    name: str = MISSING
    train: List[str] = MISSING  # conf/train.yaml overrides for every cell, after the row's
    suite: List[str] = MISSING  # conf/evaluate.yaml overrides for every cell
    curve_epochs: Optional[List[int]] = None  # the learning curve: also drive the checkpoints of these epochs
    curve_seeds: Optional[List[int]] = None  # ... in the cells of these seeds


@dataclass
class CellConfig:
    """The (row, seed) of one launcher job: set by the app."""

    row: Optional[str] = None
    seed: Optional[int] = None


@dataclass
class ReproduceConfig:
    """conf/reproduce.yaml: its own keys (their values are written there), the catalogue, claims and budget."""

    __cicfw_what__ = "the reproduce config"

    rows: List[str] = MISSING
    seeds: Any = MISSING  # a whole number or a list of seeds: ``seed_list`` checks it
    results_dir: str = MISSING
    publish_dir: Optional[str] = MISSING
    continue_from: Optional[str] = MISSING
    continue_machine: Optional[str] = MISSING
    progress_bar: bool = MISSING
    weather_family: Optional[str] = MISSING  # checked against WEATHER_FAMILIES by ``check``
    equivalence_margin: float = MISSING
    relation_candidates: List[str] = MISSING  # catalogue rows, checked by ``check``
    catalogue: Dict[str, Any] = MISSING  # row name -> ROW, checked by ``check``
    claims: List[Any] = MISSING  # CLAIM, its parts PART, checked by ``check``
    budget: BudgetConfig = field(default_factory=BudgetConfig)
    cell: CellConfig = field(default_factory=CellConfig)


#: what ``seeds`` accepts
SEEDS = (f"a whole number >= 1 (seeds 0..seeds-1 per row) or a list of distinct seeds from {SEED_RANGE[0]} to "
         f"{SEED_RANGE[1]} ([3,4])")  # the range a training run's seed takes: a cell would fail after collecting


def seed_list(seeds: Any) -> list[int]:
    """The seeds to run: ``5`` is 0..4, ``[4,3]`` those seeds only, sorted (a second machine's share of a table
    continued with ``continue_from``); anything else is one ``SchemaError`` naming ``seeds``."""
    got = list(seeds) if OmegaConf.is_list(seeds) or isinstance(seeds, (list, tuple)) else seeds
    if isinstance(got, list):
        if got and all(is_integer(x) and SEED_RANGE[0] <= x <= SEED_RANGE[1] for x in got) and len(set(got)) == len(got):
            return sorted(got)
    elif is_integer(got) and 1 <= got <= SEED_RANGE[1] + 1:
        return list(range(got))
    raise SchemaError(f"seeds must be {SEEDS}, got {got!r}", "seeds", "wrong type")


#: (schema, item as JSON) that passed: a plan is checked at each compose (the app's, each cell's), and
#: OmegaConf's check of one item costs about 7 ms, 0.4 s for the shipped catalogue and claims
_PASSED: set[tuple[type, str]] = set()


def _checked_item(schema: type, value: Any, where: str) -> dict:
    """One catalogue row, claim or part against its schema, ``where`` its full key (``claims[0].parts[1]``)."""
    if not isinstance(value, dict):
        raise SchemaError(f"{where} must be a mapping, got {value!r}", where, "wrong type")
    seen = (schema, json.dumps(value, sort_keys=True, default=repr))  # what passes does not depend on ``where``
    if seen not in _PASSED:
        checked(schema, value, where)
        _PASSED.add(seen)
    return value


def check(cfg: DictConfig) -> None:
    """What composing let through in a reproduce config (``check_composed``): a key added with ``+`` anywhere,
    ``seeds``, ``weather_family``, every catalogue row and claim, the curve's lists, the margin. One error
    naming the full key."""
    check_composed(cfg, ReproduceConfig)
    values = plain_values(cfg)
    for name, row in values["catalogue"].items():
        paper = _checked_item(ROW, row, f"catalogue.{name}").get("paper")
        if paper is not None and len(paper) != PAPER_VALUES:
            raise ConfigError(f"catalogue.{name}.paper", paper, f"the paper's {PAPER_VALUES} Table-4 values "
                              f"(training town: training / new weathers, new town: training / new weathers) or null")
    for i, claim in enumerate(values["claims"]):
        for j, part in enumerate(_checked_item(CLAIM, claim, f"claims[{i}]")["parts"]):
            _checked_item(PART, part, f"claims[{i}].parts[{j}]")
    unknown = [r for r in values["relation_candidates"] if r not in values["catalogue"]]
    if unknown:
        raise SchemaError(f"relation_candidates names {', '.join(map(repr, unknown))}, not a catalogue row; give rows of "
                          f"catalogue: ({', '.join(values['catalogue'])})", "relation_candidates", "wrong type")
    seed_list(values.get("seeds"))
    # read only after a cell has trained: a bad one is refused here instead of failing every curve cell
    for key, least, what in (("curve_seeds", 0, "seeds whose cells also drive earlier epochs"),
                             ("curve_epochs", 1, "epochs after which those cells' checkpoints are driven")):
        got = values["budget"].get(key) or []
        if any(x < least for x in got):
            raise ConfigError(f"budget.{key}", got, f"a list of whole numbers >= {least} ({what}, e.g. [1]) or null")
    check_margin(values["equivalence_margin"])  # the report needs it after every cell: checked first
    family = values.get("weather_family")
    if family is not None and family not in WEATHER_FAMILIES:
        raise SchemaError(f"weather_family must be one of {', '.join(WEATHER_FAMILIES)} or null (the simulator's "
                          f"default), got {family!r}", "weather_family", "wrong type")


ConfigStore.instance().store(name="cicfw_reproduce", node=ReproduceConfig, provider="cicfw")
