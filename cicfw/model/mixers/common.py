"""Kwarg checks shared by the mixers built from CIL branch MLPs (one message per bad value)."""
from __future__ import annotations


def check_branch_kwargs(hidden: object, dropout: object) -> None:
    """The branch MLP's width and dropout, as ``independent`` takes them."""
    check_positive_int("hidden", hidden, "the branch width (CIL: 256)")
    if isinstance(dropout, bool) or not isinstance(dropout, (int, float)) or not 0.0 <= dropout < 1.0:
        raise ValueError(f"mixer.dropout={dropout!r} is not valid; use a probability in [0, 1) (CIL: 0.5)")


def check_positive_int(name: str, value: object, what: str) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"mixer.{name}={value!r} is not valid; use a positive integer, {what}")


def check_unit_interval(name: str, value: object, what: str) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 <= value <= 1.0:
        raise ValueError(f"mixer.{name}={value!r} is not valid; use a number in [0, 1], {what}")
