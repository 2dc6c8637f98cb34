"""The train/validation split settings a run's checkpoints record, so that a resumed run validates on the
episodes it validated on before: another ``data.seed`` or ``data.val_fraction`` would move episodes the
model trained on into the validation set, and its validation error (and best checkpoint) would be wrong."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

from omegaconf import OmegaConf

from cicfw.core.config_checks import same_value
from cicfw.core.errors import CicfwError

#: the checkpoint key holding the split settings
SPLIT_KEY = "cicfw_split"
#: the ``data.*`` keys that decide which episodes validate (with the file set, which provenance checks)
SPLIT_KEYS = ("seed", "val_fraction")


def split_settings(data_cfg: Mapping[str, Any]) -> dict[str, Any]:
    """``data.seed`` and ``data.val_fraction`` of a run's ``data`` node."""
    return {key: data_cfg.get(key) for key in SPLIT_KEYS}


def run_config_split(checkpoint: Path) -> dict[str, Any] | None:
    """The split settings of the run that wrote ``checkpoint`` (``<run>/checkpoints/x.ckpt``), read from its
    ``<run>/.hydra/config.yaml``: for checkpoints written before they recorded their split. None when there
    is no such config or it does not say."""
    config = checkpoint.parent.parent / ".hydra" / "config.yaml"
    if not config.is_file():
        return None
    try:
        data = OmegaConf.load(config).get("data")
        found = {key: OmegaConf.select(data, key, throw_on_resolution_failure=True) for key in SPLIT_KEYS}
    except Exception:  # an unreadable or unresolvable config says nothing about the split
        return None
    return found if all(value is not None for value in found.values()) else None


def recorded_split(ckpt: Mapping[str, Any], checkpoint: Path) -> dict[str, Any] | None:
    """The split settings ``checkpoint`` trained with: its own record, else its run's saved config."""
    saved = ckpt.get(SPLIT_KEY)
    if isinstance(saved, Mapping):
        return dict(saved)
    return run_config_split(checkpoint)


def check_resumed_split(path: str | Path, ckpt: Mapping[str, Any], split: Mapping[str, Any]) -> None:
    """Refuse resuming ``ckpt`` with split settings other than the ones it trained with, naming each key
    and both values (a checkpoint that records none, and has no run config, is not checked)."""
    saved = recorded_split(ckpt, Path(path).expanduser())
    if saved is None:
        return
    differ = [key for key in SPLIT_KEYS if key in saved and not same_value(split.get(key), saved[key])]
    if differ:
        said = ", ".join(f"data.{key}={split.get(key)} (the checkpoint's: {saved[key]})" for key in differ)
        raise CicfwError(f"ckpt_path={path}: {said} would split the episodes into training and validation "
                         f"otherwise than the run that trained it, so episodes it trained on would validate; resume "
                         f"with the checkpoint's values, or start a fresh run (no ckpt_path) with the new ones",
                         key=f"data.{differ[0]}", value=split.get(differ[0]))
