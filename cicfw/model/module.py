"""CICModule: the ``SteeringNet`` (cicfw/model/net.py) with its training, as a thin LightningModule.

Every constructor argument is a name or plain data, so ``save_hyperparameters()`` holds the whole
model and ``CICModule.load_from_checkpoint(path)`` rebuilds it without Hydra; driving rebuilds only
the ``SteeringNet`` from the same hyper-parameters and weights (``cicfw.model.checkpoint.load_model``).
"""
from __future__ import annotations

import math
from typing import Any, Callable, Mapping

import lightning as L
import torch
from torchmetrics import MeanAbsoluteError, MeanMetric
from torchmetrics.classification import MulticlassAccuracy

from cicfw import COMMANDS
from cicfw.core.errors import ConfigError
from cicfw.core.config_checks import is_number
from cicfw.model.net import SteeringNet


def cosine_factor(total_steps: int, final: float) -> Callable[[int], float]:
    """lr(step) / lr: half a cosine from 1 at the first step to ``final`` after ``total_steps``."""
    return lambda step: final + (1.0 - final) * 0.5 * (1.0 + math.cos(math.pi * min(step, total_steps) / total_steps))


def with_warmup(factor: Callable[[int], float], warmup: int) -> Callable[[int], float]:
    """``factor`` after ``warmup`` steps whose lr rises linearly to the full lr (step ``warmup - 1``
    takes it whole), so Adam's first, poorly scaled steps are small ones."""
    return lambda step: (step + 1) / warmup if step < warmup else factor(step - warmup)


#: the learning-rate schedules over a run (``model.lr_schedule``); the paper names none, so the
#: default stays constant. ``cosine`` ends a short run with small steps instead of on a knife edge.
LR_SCHEDULES: dict[str, Callable[[int, float], Callable[[int], float] | None]] = {
    "constant": lambda total, final: None,
    "cosine": cosine_factor,
}


class CICModule(SteeringNet, L.LightningModule):
    """A thin LightningModule: the agent is the ``SteeringNet`` it extends; this adds training."""

    def __init__(
        self,
        encoder: str = "cil",
        encoder_kwargs: Mapping[str, Any] | None = None,
        mixer: str = "independent",
        mixer_kwargs: Mapping[str, Any] | None = None,
        head: str = "regression",
        head_kwargs: Mapping[str, Any] | None = None,
        speed_norm_kmh: float = 40.0,
        lr: float = 2e-4,
        betas: tuple[float, float] = (0.7, 0.85),
        weight_decay: float = 0.0,
        lr_schedule: str = "constant",
        lr_final_factor: float = 0.0,
        lr_warmup_fraction: float = 0.0,
        ema_decay: float = 0.0,
    ) -> None:
        # each number checked here, before any data, not by Adam inside fit (nan too: Adam names no key)
        for key, value, ok, accepted in (
                ("lr", lr, lambda v: v > 0, "a number > 0"),
                ("weight_decay", weight_decay, lambda v: v >= 0, "a number >= 0"),
                ("lr_final_factor", lr_final_factor, lambda v: 0.0 <= v <= 1.0, "a number in [0, 1]"),
                ("lr_warmup_fraction", lr_warmup_fraction, lambda v: 0.0 <= v < 1.0, "a number in [0, 1)"),
                ("ema_decay", ema_decay, lambda v: 0.0 <= v < 1.0, "a number in [0, 1) (0: no averaging)")):
            if not (is_number(value) and ok(value)):
                raise ConfigError(f"model.{key}", value, accepted)
        if not (isinstance(betas, (list, tuple)) and len(betas) == 2 and all(is_number(b) and 0.0 <= b < 1.0
                                                                             for b in betas)):
            raise ConfigError("model.betas", list(betas) if isinstance(betas, (list, tuple)) else betas,
                              "two numbers in [0, 1), e.g. [0.7,0.85]")
        if lr_schedule not in LR_SCHEDULES:
            raise ConfigError("model.lr_schedule", lr_schedule, f"one of {', '.join(LR_SCHEDULES)}",
                             f"model.lr_schedule={lr_schedule!r} is not known; use one of {', '.join(LR_SCHEDULES)}")
        if lr_schedule == "constant" and lr_final_factor != 0.0:  # where cosine ends: constant never reads it
            raise ConfigError("model.lr_final_factor", lr_final_factor, "0.0 with model.lr_schedule=constant",
                              f"model.lr_final_factor={lr_final_factor} is unused by model.lr_schedule=constant; "
                              f"give model.lr_schedule=cosine, or leave model.lr_final_factor at 0.0")
        super().__init__(encoder=encoder, encoder_kwargs=encoder_kwargs, mixer=mixer, mixer_kwargs=mixer_kwargs,
                         head=head, head_kwargs=head_kwargs, speed_norm_kmh=speed_norm_kmh)
        self.save_hyperparameters()
        self.adam_impl = "for-loop"  # speed switches (cicfw/model/speed.py): not hyper-parameters
        self._compiled_step = None
        for stage in ("train", "val"):
            setattr(self, f"{stage}_mae", MeanAbsoluteError())
        self.val_mae_per_command = torch.nn.ModuleList(MeanAbsoluteError() for _ in COMMANDS)
        self.val_loss = MeanMetric()
        self.val_bin_acc = (
            MulticlassAccuracy(num_classes=self.head.bins.n, average="micro") if self.head.bins else None
        )

    def enable_compile(self) -> "CICModule":
        """torch.compile the training step (forward + loss, with its backward); validation and
        inference stay eager. The compiled function is not a submodule, so ``state_dict`` keys are
        unchanged (no ``_orig_mod.`` prefix). Compilation happens on the first training step."""
        self._compiled_step = torch.compile(self._step_outputs)
        return self

    def disable_compile(self) -> "CICModule":
        self._compiled_step = None
        return self

    def __getstate__(self) -> dict:  # a compiled function does not pickle; recompile after unpickling
        return {**super().__getstate__(), "_compiled_step": None}

    # ---- training ----------------------------------------------------------------------------
    def _step_outputs(self, image: torch.Tensor, speed: torch.Tensor, command: torch.Tensor,
                      steer: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        out = self(image, speed, command)
        task = self.head.loss(out, steer)
        return task, task + self.mixer.regularizer(), out

    def _losses(self, batch: Mapping[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        step = self._compiled_step if self._compiled_step is not None and self.training else self._step_outputs
        return step(batch["image"], batch["speed"], batch["command"], batch["steer"])

    def training_step(self, batch: Mapping[str, torch.Tensor], batch_idx: int) -> torch.Tensor:
        task, loss, out = self._losses(batch)
        n = batch["steer"].shape[0]
        self.train_mae(self.head.decode(out.detach()), batch["steer"].contiguous())
        self.log("train/loss", loss, prog_bar=True, batch_size=n)
        self.log("train/task_loss", task, batch_size=n)
        self.log("train/steer_mae", self.train_mae, on_step=False, on_epoch=True, batch_size=n)
        return loss

    def validation_step(self, batch: Mapping[str, torch.Tensor], batch_idx: int) -> None:
        task, _, out = self._losses(batch)
        steer, command = batch["steer"].contiguous(), batch["command"]
        pred = self.head.decode(out)
        n = steer.shape[0]
        self.val_loss.update(task, weight=n)
        self.val_mae.update(pred, steer)
        for i, metric in enumerate(self.val_mae_per_command):
            mask = command == i
            if mask.any():
                metric.update(pred[mask], steer[mask].contiguous())
        if self.val_bin_acc is not None:
            self.val_bin_acc.update(self.head.predict_class(out), self.head.bins.to_class(steer))

    def on_validation_epoch_end(self) -> None:
        self.log("val/loss", self.val_loss.compute())
        self.log("val/steer_mae", self.val_mae.compute(), prog_bar=True)
        self.val_loss.reset()
        self.val_mae.reset()
        for name, metric in zip(COMMANDS, self.val_mae_per_command):
            if metric.update_called:
                self.log(f"val/steer_mae/{name}", metric.compute())
            metric.reset()
        if self.val_bin_acc is not None:
            self.log("val/bin_acc", self.val_bin_acc.compute())
            self.val_bin_acc.reset()

    def configure_optimizers(self) -> Any:
        hp = self.hparams
        impl = {"fused": {"fused": True}, "foreach": {"foreach": True}}.get(self.adam_impl, {"foreach": False})
        opt = torch.optim.Adam(self.parameters(), lr=hp.lr, betas=tuple(hp.betas), weight_decay=hp.weight_decay,
                               **impl)
        schedule = hp.get("lr_schedule", "constant")  # checkpoints written before schedules existed
        warmup_fraction = float(hp.get("lr_warmup_fraction", 0.0))
        if schedule == "constant" and warmup_fraction == 0.0:
            return opt
        total = max(int(self.trainer.estimated_stepping_batches), 1)
        warmup = min(round(warmup_fraction * total), total - 1)
        after = LR_SCHEDULES[schedule](total - warmup, float(hp.get("lr_final_factor", 0.0))) or (lambda step: 1.0)
        factor = with_warmup(after, warmup)
        return {"optimizer": opt,
                "lr_scheduler": {"scheduler": torch.optim.lr_scheduler.LambdaLR(opt, factor), "interval": "step"}}
