"""Kwarg checks shared by the mixers built from CIL branch MLPs (one message per bad value)."""
from __future__ import annotations

from cicfw.core.errors import ConfigError


def _is_prob(p: object) -> bool:
    return not isinstance(p, bool) and isinstance(p, (int, float)) and 0.0 <= p < 1.0


def branch_dropouts(dropout: object) -> tuple[float, float]:
    """The dropout after each of a branch's two hidden layers: a pair, or one number for both.

    The CIL authors' released network drops 0.5 after the first hidden layer and nothing after the
    second (``[0.5, 0.0]``, cicfw's default); a single number (cicfw 0.1's default 0.5) applies to both,
    so older checkpoints keep their meaning.
    """
    pair = tuple(dropout) if isinstance(dropout, (list, tuple)) else (dropout, dropout)
    if len(pair) != 2 or not all(_is_prob(p) for p in pair):
        raise ConfigError("mixer.dropout", dropout, "a probability in [0, 1) or a pair of them",
                         f"mixer.dropout={dropout!r} is not valid; use a probability in [0, 1) or a pair of them, "
                         "one per hidden layer (CIL's released network: [0.5, 0.0])")
    return float(pair[0]), float(pair[1])


def check_branch_kwargs(hidden: object, dropout: object) -> None:
    """The branch MLP's width and dropout, as ``independent`` takes them."""
    check_positive_int("hidden", hidden, "the branch width (CIL: 256)")
    branch_dropouts(dropout)


def check_positive_int(name: str, value: object, what: str) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ConfigError(f"mixer.{name}", value, "a positive integer",
                         f"mixer.{name}={value!r} is not valid; use a positive integer, {what}")


def check_unit_interval(name: str, value: object, what: str) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 <= value <= 1.0:
        raise ConfigError(f"mixer.{name}", value, "a number in [0, 1]",
                         f"mixer.{name}={value!r} is not valid; use a number in [0, 1], {what}")
