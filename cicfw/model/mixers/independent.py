"""``independent``: plain CIL, four branches that never see each other (Codevilla et al. 2018)."""
from __future__ import annotations

import torch
from torch import nn

from cicfw.model.mixers.base import Mixer
from cicfw.model.mixers.common import check_branch_kwargs
from cicfw.registry import MIXERS


def branch_mlp(in_dim: int, hidden: int, out_dim: int, dropout: float = 0.5) -> nn.Sequential:
    """One CIL branch: in -> hidden -> hidden -> out, ReLU and dropout between."""
    return nn.Sequential(
        nn.Linear(in_dim, hidden), nn.ReLU(inplace=True), nn.Dropout(dropout),
        nn.Linear(hidden, hidden), nn.ReLU(inplace=True), nn.Dropout(dropout),
        nn.Linear(hidden, out_dim),
    )


@MIXERS.register("independent")
class IndependentMixer(Mixer):
    """CIL: one MLP 512 -> 256 -> 256 -> K per command, no sharing between branches."""

    def __init__(self, in_dim: int, out_dim: int, hidden: int = 256, dropout: float = 0.5) -> None:
        super().__init__(in_dim, out_dim)
        check_branch_kwargs(hidden, dropout)
        self.branches = nn.ModuleList(
            branch_mlp(in_dim, hidden, out_dim, dropout) for _ in range(self.n_branches)
        )

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        return torch.stack([branch(h) for branch in self.branches], dim=1)
