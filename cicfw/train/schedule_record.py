"""The settings a run's learning-rate schedule is spread over, recorded in its checkpoints: a cosine decay or
a warm-up is laid over the run's estimated steps, which a resumed run recomputes from its own settings, so
resuming with more epochs (or other batches) would bend the schedule mid-run (the rate rising again after
it had decayed) rather than follow one schedule over the whole run."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

from omegaconf import OmegaConf

from cicfw.core.config_checks import plain_value, same_value
from cicfw.core.errors import CicfwError
from cicfw.core.run_folder import saved_run_config

#: the checkpoint key holding the settings
SCHEDULE_KEY = "cicfw_schedule"
#: the settings ``Trainer.estimated_stepping_batches`` (the schedule's length) follows, as full config keys;
#: the data's size is pinned by the data record (``cicfw.data.provenance``)
HORIZON_KEYS = ("trainer.max_epochs", "trainer.max_steps", "trainer.limit_train_batches",
                "trainer.accumulate_grad_batches", "trainer.devices", "trainer.num_nodes",
                "data.batch_size", "data.batches_per_epoch")


def step_shaped(model_hparams: Mapping[str, Any]) -> bool:
    """Whether the learning rate depends on the run's length: a schedule other than ``constant``, or a warm-up."""
    return (model_hparams.get("lr_schedule", "constant") != "constant"
            or float(model_hparams.get("lr_warmup_fraction", 0.0) or 0.0) > 0.0)


def horizon_settings(cfg: Any) -> dict[str, Any]:
    """The ``HORIZON_KEYS`` of a train config (a key it does not set is None: Lightning's default)."""
    return {key: plain_value(OmegaConf.select(cfg, key, default=None)) for key in HORIZON_KEYS}


def run_config_horizon(checkpoint: Path) -> dict[str, Any] | None:
    """The settings of the run that wrote ``checkpoint`` (``<run>/checkpoints/x.ckpt``), from its
    ``<run>/.hydra/config.yaml``: for checkpoints written before they recorded them. None when there is none."""
    config = saved_run_config(checkpoint)
    if config is None:
        return None
    try:
        return horizon_settings(config)
    except Exception:  # an unresolvable config says nothing about the schedule
        return None


def check_resumed_horizon(path: str | Path, ckpt: Mapping[str, Any], model_hparams: Mapping[str, Any],
                          horizon: Mapping[str, Any]) -> None:
    """Refuse resuming ``ckpt`` under a step-shaped schedule with settings that change the run's length,
    naming each key and both values (a constant rate without warm-up may train on for as long as asked)."""
    if not step_shaped(model_hparams):
        return
    saved = ckpt.get(SCHEDULE_KEY)
    saved = dict(saved) if isinstance(saved, Mapping) else run_config_horizon(Path(path).expanduser())
    if saved is None:
        return
    differ = [key for key in HORIZON_KEYS if key in saved and not same_value(horizon.get(key), saved[key])]
    if differ:
        said = ", ".join(f"{key}={horizon.get(key)} (the checkpoint's: {saved[key]})" for key in differ)
        schedule = model_hparams.get("lr_schedule", "constant")
        raise CicfwError(f"ckpt_path={path}: {said} would change the number of steps the learning-rate schedule "
                         f"(model.lr_schedule={schedule}, model.lr_warmup_fraction="
                         f"{model_hparams.get('lr_warmup_fraction', 0.0)}) is spread over, bending it mid-run; resume "
                         f"with the checkpoint's values, or start a fresh run (no ckpt_path) with the new ones",
                         key=differ[0], value=horizon.get(differ[0]))
