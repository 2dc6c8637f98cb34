"""``regression``: CIL's scalar steering output with an MSE (or L1) loss."""
from __future__ import annotations

import torch
import torch.nn.functional as F

from cicfw.core.errors import ConfigError
from cicfw.model.heads.base import Head
from cicfw.registry import HEADS

_LOSSES = {"mse": F.mse_loss, "l1": F.l1_loss}


@HEADS.register("regression")
class RegressionHead(Head):
    """K = 1; decode clamps to [-1, 1]."""

    def __init__(self, loss: str = "mse") -> None:
        super().__init__()
        if loss not in _LOSSES:
            raise ConfigError("head.loss", loss, f"one of {sorted(_LOSSES)}",
                             f"head.loss={loss!r} is not known; use one of {sorted(_LOSSES)}")
        self.out_dim = 1
        self.loss_name = loss

    def loss(self, out: torch.Tensor, steer: torch.Tensor) -> torch.Tensor:
        return _LOSSES[self.loss_name](out[:, 0], steer)

    def decode(self, out: torch.Tensor) -> torch.Tensor:
        return out[:, 0].clamp(-1.0, 1.0)
