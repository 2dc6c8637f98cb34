"""``independent``: plain CIL, four branches that never see each other (Codevilla et al. 2018)."""
from __future__ import annotations

from typing import Sequence

import torch
from torch import nn

from cicfw.model.mixers.base import Mixer
from cicfw.model.mixers.common import branch_dropouts, check_branch_kwargs
from cicfw.registry import MIXERS


def branch_mlp(in_dim: int, hidden: int, out_dim: int,
               dropout: float | Sequence[float] = (0.5, 0.0)) -> nn.Sequential:
    """One CIL branch: in -> hidden -> hidden -> out, ReLU and dropout between (per hidden layer:
    ``dropout`` is a pair, or one number for both). Dropout(0) layers are kept so the layer indices
    (and ``state_dict`` keys) do not depend on the rates."""
    p1, p2 = branch_dropouts(dropout)
    return nn.Sequential(
        nn.Linear(in_dim, hidden), nn.ReLU(inplace=True), nn.Dropout(p1),
        nn.Linear(hidden, hidden), nn.ReLU(inplace=True), nn.Dropout(p2),
        nn.Linear(hidden, out_dim),
    )


@MIXERS.register("independent")
class IndependentMixer(Mixer):
    """CIL: one MLP 512 -> 256 -> 256 -> K per command, no sharing between branches."""

    def __init__(self, in_dim: int, out_dim: int, hidden: int = 256,
                 dropout: float | Sequence[float] = (0.5, 0.0)) -> None:
        super().__init__(in_dim, out_dim)
        check_branch_kwargs(hidden, dropout)
        self.branches = nn.ModuleList(
            branch_mlp(in_dim, hidden, out_dim, dropout) for _ in range(self.n_branches)
        )

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        return torch.stack([branch(h) for branch in self.branches], dim=1)
