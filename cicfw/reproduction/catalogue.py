"""A row of the reproduction's catalogue (``catalogue.<row>`` in conf/reproduce.yaml): the one place its keys
and types live. A cell trains the row's ``experiment`` with its ``overrides``; the report shows its ``label``
beside ``paper``, the paper's Table-4 values. The reproduce config's schema (cicfw/reproduce_schema) takes
a row's keys from ``Row``."""
from dataclasses import dataclass, field
from typing import List, Optional

#: Table 4's columns, the values ``paper`` holds: training town (training / new weathers), new town (same)
PAPER_VALUES = 4


@dataclass
class Row:
    """One catalogue row."""

    experiment: str  # conf/experiment/<name>, e.g. paper_gtu
    label: str  # the row's name in the report
    overrides: List[str] = field(default_factory=list)  # train overrides after the experiment's
    paper: Optional[List[float]] = None  # the paper's PAPER_VALUES Table-4 values, or null
