"""The Mixer contract: what every branch mixer (built-in or plugin) provides."""
from __future__ import annotations

import torch
from torch import nn

from cicfw import N_COMMANDS


class Mixer(nn.Module):
    """Owns the command branches: maps shared features ``h`` (B, in_dim) to (B, 4, out_dim).

    Branch order is [follow, left, right, straight] (CIL command code - 2). The module picks
    ``out[b, command[b]]``, so a mixer never sees the command. Subclasses are built as
    ``cls(in_dim=..., out_dim=..., **kwargs_from_config)`` and must validate their kwargs in
    ``__init__`` with a clear ``ValueError`` (never a shape error at the first step).
    """

    n_branches: int = N_COMMANDS

    def __init__(self, in_dim: int, out_dim: int) -> None:
        super().__init__()
        self.in_dim = in_dim
        self.out_dim = out_dim

    def forward(self, h: torch.Tensor) -> torch.Tensor:  # (B, in_dim) -> (B, 4, out_dim)
        raise NotImplementedError

    def regularizer(self) -> torch.Tensor:
        """A scalar added to the loss (already weighted); zero unless the method has one."""
        return next(self.parameters()).new_zeros(())

    def inspect(self) -> dict[str, torch.Tensor]:
        """Matrices worth looking at from the last forward, for logging.

        A value shaped (B, r, c) is per sample (the logger averages it per command);
        a value shaped (r, c) is global (e.g. learned cross-stitch alphas). Empty by default.
        """
        return {}
