"""The data settings a run's checkpoints record, so that a resumed run trains and validates on the samples it
did before: another ``data.seed`` or ``data.val_fraction`` would move episodes the model trained on into the
validation set, and other cameras, steering filter or side-camera correction would change which samples (and
labels) train and validate, so its validation error (and best checkpoint) would be wrong."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

from omegaconf import OmegaConf

from cicfw.core.config_checks import plain_value, same_value
from cicfw.core.errors import CicfwError
from cicfw.core.run_folder import saved_run_config
from cicfw.model.checkpoint import SPLIT_KEY

#: the ``data.*`` keys that decide which episodes validate (with the file set, which provenance checks)
SPLIT_KEYS = ("seed", "val_fraction")
#: the ``data.*`` keys that decide which samples of those episodes train and validate, and their labels
SAMPLE_KEYS = ("cameras", "val_cameras", "max_abs_steer", "side_camera_correction")
#: every key recorded (checkpoints written before the sample keys recorded the split keys only)
RECORDED_KEYS = SPLIT_KEYS + SAMPLE_KEYS


def split_settings(data_cfg: Mapping[str, Any]) -> dict[str, Any]:
    """The ``RECORDED_KEYS`` of a run's ``data`` node (a key it lacks: not recorded, so never compared)."""
    return {key: plain_value(data_cfg.get(key)) for key in RECORDED_KEYS if key in data_cfg}


def run_config_split(checkpoint: Path) -> dict[str, Any] | None:
    """The settings of the run that wrote ``checkpoint`` (``<run>/checkpoints/x.ckpt``), read from its
    ``<run>/.hydra/config.yaml``: for checkpoints written before they recorded them. None when there is no
    such config or it does not give the split; a key it lacks or cannot resolve is left out."""
    config = saved_run_config(checkpoint)
    data = config.get("data") if config is not None else None
    if not OmegaConf.is_dict(data):
        return None
    found = {}
    for key in RECORDED_KEYS:
        try:
            if key in data:
                found[key] = plain_value(OmegaConf.select(data, key, throw_on_resolution_failure=True))
        except Exception:  # an unresolvable value says nothing
            continue
    return found if all(found.get(key) is not None for key in SPLIT_KEYS) else None


def recorded_split(ckpt: Mapping[str, Any], checkpoint: Path) -> dict[str, Any] | None:
    """The settings ``checkpoint`` trained with: its own record, completed by its run's saved config for the
    keys the record lacks (an older checkpoint recorded the split keys only)."""
    saved = ckpt.get(SPLIT_KEY)
    own = dict(saved) if isinstance(saved, Mapping) else None
    if own is not None and all(key in own for key in RECORDED_KEYS):
        return own
    config = run_config_split(checkpoint)
    if own is None:
        return config
    return {**(config or {}), **own}


def check_resumed_split(path: str | Path, ckpt: Mapping[str, Any], split: Mapping[str, Any]) -> None:
    """Refuse resuming ``ckpt`` with data settings other than the ones it trained with, naming each key
    and both values (a checkpoint that records none, and has no run config, is not checked)."""
    saved = recorded_split(ckpt, Path(path).expanduser())
    if saved is None:
        return
    differ = [key for key in RECORDED_KEYS if key in saved and key in split and not same_value(split[key], saved[key])]
    if differ:
        said = ", ".join(f"data.{key}={split[key]} (the checkpoint's: {saved[key]})" for key in differ)
        why = ("would split the episodes into training and validation otherwise than the run that trained it, so "
               "episodes it trained on would validate" if differ[0] in SPLIT_KEYS else
               "would train and validate on other samples (or labels) than the run that trained it, so its "
               "validation error would not be comparable across the resume")
        raise CicfwError(f"ckpt_path={path}: {said} {why}; resume with the checkpoint's values, or start a fresh "
                         f"run (no ckpt_path) with the new ones", key=f"data.{differ[0]}", value=split[differ[0]])
