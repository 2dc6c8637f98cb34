"""What a checkpoint's inputs and outputs mean must not change when training resumes from it: another speed
scale, or other steering bins or phases of the same shapes, would load the weights unchanged, train on with
the new meaning and record only the new one, so the model would be neither (a mixer or head names its own
such kwargs in ``kept_on_resume``); another ``re`` R would be replaced by the checkpoint's and trained with,
while the run records the new one. Another encoder, mixer or head whose weights happen to fit (a plugin's)
is another model; only a binned head may become another binned head (softmax, coexistence, hybrid: the same
bins, another loss)."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

from cicfw.core.config_checks import same_value
from cicfw.core.errors import CicfwError
from cicfw.model.heads.binned import BinnedHead
from cicfw.registry import HEADS, MIXERS

#: ``model.*`` values that say how the encoder reads its input
INPUT_KEYS = ("speed_norm_kmh",)
#: ``head.*`` values that say what the head's outputs mean (the built-in heads' bins and sine phases)
OUTPUT_KEYS = ("n_classes", "low", "high", "bin_width", "n_units", "phase_range")
#: ``mixer.*`` values kept in a persistent buffer (re's R): the checkpoint's would replace this run's unsaid
MIXER_KEYS = ("R",)


def changed_encoding(saved: Mapping[str, Any], ours: Mapping[str, Any]) -> list[tuple[str, Any, Any]]:
    """(key, this run's value, the checkpoint's) for each key whose meaning differs between the checkpoint's
    hyper-parameters ``saved`` and this run's ``ours`` (a key the checkpoint does not record is not compared)."""
    differ = [(f"model.{k}", ours.get(k), saved[k]) for k in INPUT_KEYS
              if k in saved and not same_value(ours.get(k), saved[k])]
    differ += [(node, ours.get(node), saved[node]) for node in ("encoder", "mixer", "head")
               if saved.get(node) not in (None, ours.get(node)) and not (node == "head" and _binned(saved[node])
                                                                       and _binned(ours.get(node)))]
    for node, keys in (("head", OUTPUT_KEYS), ("mixer", MIXER_KEYS)):
        keys = (*keys, *getattr(_part(node, ours.get(node)), "kept_on_resume", ()))  # a plugin's own
        if saved.get(node) == ours.get(node) or node == "head":  # binned heads of other names: same bins
            theirs, mine = saved.get(f"{node}_kwargs") or {}, ours.get(f"{node}_kwargs") or {}
            differ += [(f"{node}.{k}", mine[k], theirs[k]) for k in keys
                       if k in theirs and k in mine and not same_value(mine[k], theirs[k])]
    return differ


def _part(node: str, name: Any) -> type | None:
    """The registered class of the head or mixer ``name`` (None when there is none)."""
    try:
        return (HEADS if node == "head" else MIXERS).get(str(name))
    except KeyError:
        return None


def _binned(name: Any) -> bool:
    """Whether the registered head ``name`` is a binned classification head (its outputs are bins' scores)."""
    return issubclass(_part("head", name) or object, BinnedHead)


def check_resumed_encoding(path: str | Path, saved: Mapping[str, Any], ours: Mapping[str, Any]) -> None:
    """Refuse resuming a checkpoint whose input scale or output encoding this run would change."""
    differ = changed_encoding(saved, ours)
    if differ:
        said = ", ".join(f"{key}={now} (the checkpoint's: {then})" for key, now, then in differ)
        raise CicfwError(f"ckpt_path={path}: {said} would give the checkpoint's weights another meaning than they "
                         f"were trained with; resume with the checkpoint's values, or start a fresh run (no "
                         f"ckpt_path) with the new ones", key=differ[0][0], value=differ[0][1])
