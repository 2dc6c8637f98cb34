"""``python -m cicfw.train``: compose encoder/mixer/head/data/trainer from the config and fit.

Returns the validation metric (``optimized_metric``) so Hydra sweepers can optimise it.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Callable

import hydra
import lightning as L
import torch
from lightning.pytorch.callbacks import Callback, ModelCheckpoint, RichProgressBar
from lightning.pytorch.loggers import CSVLogger, Logger, TensorBoardLogger
from omegaconf import DictConfig, OmegaConf

from cicfw.data.datamodule import CILDataModule
from cicfw.errors import report_user_errors
from cicfw.model.diagnostics import MixerDiagnostics
from cicfw.model.module import CICModule
from cicfw.model.speed import apply_speed_from_config

log = logging.getLogger("cicfw.train")

# Trainer-config keys that are cicfw switches rather than Lightning Trainer arguments.
SPEED_SWITCHES = ("compile", "channels_last", "adam")

LOGGERS: dict[str, Callable[[Path], Logger]] = {
    "csv": lambda run_dir: CSVLogger(str(run_dir), name="csv", version=""),
    "tensorboard": lambda run_dir: TensorBoardLogger(str(run_dir), name="tensorboard", version=""),
}


def name_and_kwargs(node: DictConfig) -> tuple[str, dict[str, Any]]:
    """A config-group node is ``name:`` plus the constructor's keyword arguments."""
    d = OmegaConf.to_container(node, resolve=True)
    assert isinstance(d, dict)
    if "name" not in d:
        raise ValueError(f"config node {d} has no 'name:' key naming the registered class")
    return d.pop("name"), d


def build_model(cfg: DictConfig) -> CICModule:
    enc, enc_kw = name_and_kwargs(cfg.encoder)
    mix, mix_kw = name_and_kwargs(cfg.mixer)
    head, head_kw = name_and_kwargs(cfg.head)
    model = CICModule(encoder=enc, encoder_kwargs=enc_kw, mixer=mix, mixer_kwargs=mix_kw,
                      head=head, head_kwargs=head_kw, **OmegaConf.to_container(cfg.model, resolve=True))
    if cfg.trainer.get("channels_last"):
        model.use_channels_last()
    return model


def ensure_data(data_cfg: DictConfig) -> None:
    """Collect (or finish collecting) the default simulator dataset; a complete one returns at once.

    Asking the collector every time, rather than testing for files, means a collection that was
    killed half-way is finished instead of silently training on part of the data.
    """
    if data_cfg.get("collect") is None:
        return
    from cicfw.collect import collect_dataset  # the simulator is only needed for the default data

    collect_dataset(data_cfg.collect, Path(data_cfg.path).expanduser())


def build_datamodule(cfg: DictConfig) -> CILDataModule:
    ensure_data(cfg.data)
    kwargs = OmegaConf.to_container(cfg.data, resolve=True)
    kwargs.pop("collect", None)
    kwargs["path"] = str(Path(kwargs["path"]).expanduser())
    return CILDataModule(**kwargs)


class EpochCheckpoints(Callback):
    """``checkpoints/epochNNN.ckpt`` after each listed epoch (1-based), kept: a learning curve's points."""

    def __init__(self, dirpath: Path, epochs) -> None:
        self.dirpath, self.epochs = Path(dirpath), {int(e) for e in epochs}

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        epoch = trainer.current_epoch + 1
        if epoch in self.epochs:
            trainer.save_checkpoint(str(self.dirpath / f"epoch{epoch:03d}.ckpt"))


def build_callbacks(cfg: DictConfig, run_dir: Path) -> list[Callback]:
    callbacks: list[Callback] = [
        ModelCheckpoint(dirpath=run_dir / "checkpoints", monitor=cfg.optimized_metric, mode="min",
                        save_last=True, filename="epoch{epoch:03d}-mae{val/steer_mae:.4f}",
                        auto_insert_metric_name=False),
        MixerDiagnostics(),  # heatmaps of what the mixer learned (C, gates, alphas) per validation epoch
    ]
    if cfg.get("keep_epoch_checkpoints"):
        callbacks.append(EpochCheckpoints(run_dir / "checkpoints", cfg.keep_epoch_checkpoints))
    if cfg.get("progress_bar", True):
        callbacks.append(RichProgressBar())
    return callbacks


def build_trainer(cfg: DictConfig, run_dir: Path) -> L.Trainer:
    kwargs = OmegaConf.to_container(cfg.trainer, resolve=True)
    for key in SPEED_SWITCHES:
        kwargs.pop(key, None)
    if cfg.logger is None:
        logger: Logger | bool = False
    elif cfg.logger.name not in LOGGERS:
        raise ValueError(f"unknown logger {cfg.logger.name!r}; known loggers: {', '.join(sorted(LOGGERS))}")
    else:
        logger = LOGGERS[cfg.logger.name](run_dir)
    kwargs.setdefault("enable_progress_bar", bool(cfg.get("progress_bar", True)))
    return L.Trainer(default_root_dir=str(run_dir), logger=logger,
                     callbacks=build_callbacks(cfg, run_dir), **kwargs)


def train(cfg: DictConfig, run_dir: Path) -> float:
    """Fit and return the best ``cfg.optimized_metric`` (validation steer MAE by default); with
    ``evaluate_after`` run the closed-loop suite afterwards (and return its success rate, in %, when
    ``return_closed_loop``)."""
    run_dir = Path(run_dir)
    L.seed_everything(cfg.seed, workers=True)
    model = build_model(cfg)  # a bad mixer/head/encoder name fails here, before any data work
    datamodule = build_datamodule(cfg)
    datamodule.setup("fit")  # bad files and empty splits fail here, before training starts
    apply_speed_from_config(model, cfg.trainer, cfg.data.batch_size,  # compile (or its one-line fallback),
                            len(datamodule.train_dataloader()))      # channels_last, Adam's step
    trainer = build_trainer(cfg, run_dir)
    trainer.fit(model, datamodule=datamodule, ckpt_path=cfg.get("ckpt_path"))
    ckpt = trainer.checkpoint_callback
    best = ckpt.best_model_score if ckpt is not None and ckpt.best_model_score is not None else None
    value = best if best is not None else trainer.callback_metrics.get(cfg.optimized_metric)
    metric = float(value) if value is not None else float("nan")
    log.info("%s = %.4f; checkpoints in %s", cfg.optimized_metric, metric, run_dir / "checkpoints")
    if cfg.get("evaluate_after"):  # the closed-loop suite on the best checkpoint (docs/evaluation.md)
        from cicfw.evaluate import evaluate_after_training

        success = evaluate_after_training(cfg, trainer, run_dir)["success"]
        if cfg.get("return_closed_loop"):
            return float(success)
    return metric


@hydra.main(version_base="1.3", config_path="pkg://cicfw.conf", config_name="train")
@report_user_errors
def main(cfg: DictConfig) -> float:
    from hydra.core.hydra_config import HydraConfig

    return train(cfg, Path(HydraConfig.get().runtime.output_dir))


if __name__ == "__main__":
    from cicfw.override_hints import run_app

    run_app(main, "train")  # a mistyped key also prints the keys that exist (did you mean ...?)
