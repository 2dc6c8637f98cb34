"""A row of the reproduction's catalogue (``catalogue.<row>`` in conf/reproduce.yaml): the one place its keys
and types live. A cell trains the row's ``experiment`` with its ``overrides``; the report shows its ``label``
beside ``paper``, the paper's Table-4 values. The reproduce config's schema (cicfw/reproduction/schema.py) takes
a row's keys from ``Row``; ``row_overrides`` makes a cell's training overrides of its row, ``trained_overrides``
what its cell.json records of them.
"""
import re
from dataclasses import dataclass, field
from typing import Any, List, Optional, Sequence

from omegaconf import DictConfig, OmegaConf

from cicfw.model.speed import SPEED_SWITCHES

#: Table 4's columns, the values ``paper`` holds: training town (training / new weathers), new town (same)
PAPER_VALUES = 4


@dataclass
class Row:
    """One catalogue row."""

    experiment: str  # conf/experiment/<name>, e.g. paper_gtu
    label: str  # the row's name in the report
    overrides: List[str] = field(default_factory=list)  # train overrides after the experiment's
    paper: Optional[List[float]] = None  # the paper's PAPER_VALUES Table-4 values, or null


def override_key(override: Any) -> str:
    """The config key an override sets (``+trainer.limit_train_batches=2`` -> ``trainer.limit_train_batches``)."""
    return str(override).split("=", 1)[0].lstrip("+~")


def budget_settings_in_row(cfg: DictConfig, row: str) -> list[tuple[str, str]]:
    """The row's overrides of keys the cell sets after them, each with what wins: the budget's training
    overrides, the seed and the progress bar. ``row_overrides`` puts the row's first, so such an override
    would be silently ignored (a row given ``trainer.max_epochs=5`` would train the budget's epochs)."""
    after = {override_key(o): str(o) for o in speed_node_spelling(cfg.budget.train)}
    after.update({"seed": "seed=<the cell's seed>", "progress_bar": "progress_bar=<progress_bar>",
                  "experiment": f"experiment={cfg.catalogue[row].experiment}"})
    overrides = speed_node_spelling(cfg.catalogue[row].get("overrides") or [])
    return [(o, after[override_key(o)]) for o in overrides if override_key(o) in after]


def row_overrides(cfg: DictConfig, row: str, seed: int) -> list[str]:
    """conf/train.yaml overrides of one cell: the row's experiment, the budget, the seed."""
    entry = cfg.catalogue[row]
    return [f"experiment={entry.experiment}", *[str(o) for o in entry.get("overrides") or []],
            *speed_node_spelling(cfg.budget.train), f"seed={seed}",
            f"progress_bar={str(bool(cfg.progress_bar)).lower()}"]


def trained_overrides(cfg: DictConfig, row: str) -> list[str]:
    """What a cell of ``row`` records it was trained with (cell.json's ``overrides``): the row's experiment and
    catalogue overrides as resolved, then the budget's training overrides as written (as the folder pins them,
    so that a cache elsewhere is the same plan); the seed and the progress bar are not the row's definition."""
    entry = cfg.catalogue[row]
    budget = OmegaConf.to_container(cfg.budget, resolve=False)["train"]
    return speed_node_spelling([f"experiment={entry.experiment}", *[str(o) for o in entry.get("overrides") or []],
                                *[str(o) for o in budget]])


def speed_node_spelling(overrides: Sequence[Any]) -> list[str]:
    """Training overrides with the speed switches spelled ``speed.<switch>=``: a folder pinned, or a cell
    recorded, while they were keys of the trainer node says ``trainer.<switch>=`` for the same setting."""
    legacy = re.compile(rf"^trainer\.({'|'.join(SPEED_SWITCHES)})=")
    return [legacy.sub(r"speed.\1=", str(o)) for o in overrides]
