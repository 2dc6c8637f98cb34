"""``cross_stitch``: cross-stitch units between the branches (Misra et al. 2016; the paper's Sec.
"Specialist Branches Co-learning", which reports that it "failed to learn the driving task").

After each hidden layer of the CIL branches, a learned 4x4 α mixes the branches' activations:
``x'_i = Σ_j α_ij x_j``, initialised 0.9 on the diagonal and 0.1/3 elsewhere (rows sum to 1).
With α = I this is exactly ``independent``.
"""
from __future__ import annotations

from typing import Sequence

import torch
from torch import nn

from cicfw.model.mixers.common import check_unit_interval
from cicfw.model.mixers.independent import IndependentMixer
from cicfw.registry import MIXERS

# Slices of a ``branch_mlp`` Sequential: two hidden blocks (Linear, ReLU, Dropout), then the output Linear.
HIDDEN_BLOCKS = (slice(0, 3), slice(3, 6))
OUTPUT_LAYER = 6


def stitch_init(n: int, diag: float) -> torch.Tensor:
    """(n, n) with ``diag`` on the diagonal and ``(1 - diag) / (n - 1)`` elsewhere."""
    alpha = torch.full((n, n), (1.0 - diag) / (n - 1))
    alpha.fill_diagonal_(diag)
    return alpha


def run_block(branches: nn.ModuleList, block: slice, x: torch.Tensor) -> torch.Tensor:
    """Apply ``block`` of each branch k to ``x[:, k]``: (B, n, D_in) -> (B, n, D_out)."""
    return torch.stack([branch[block](x[:, k]) for k, branch in enumerate(branches)], dim=1)


@MIXERS.register("cross_stitch")
class CrossStitchMixer(IndependentMixer):
    """CIL branches with a learned 4x4 cross-stitch α after each of their two hidden layers."""

    def __init__(
        self, in_dim: int, out_dim: int, alpha_diag: float = 0.9, hidden: int = 256,
        dropout: float | Sequence[float] = (0.5, 0.0),
    ) -> None:
        check_unit_interval("alpha_diag", alpha_diag, "the initial self-weight of each branch (paper: 0.9)")
        super().__init__(in_dim, out_dim, hidden, dropout)  # the branches
        self.alphas = nn.ParameterList(nn.Parameter(stitch_init(self.n_branches, alpha_diag)) for _ in HIDDEN_BLOCKS)

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        x = h[:, None].expand(-1, self.n_branches, -1)
        for block, alpha in zip(HIDDEN_BLOCKS, self.alphas):
            x = torch.einsum("ij,bjd->bid", alpha, run_block(self.branches, block, x))
        return torch.stack([b[OUTPUT_LAYER](x[:, k]) for k, b in enumerate(self.branches)], dim=1)

    def inspect(self) -> dict[str, torch.Tensor]:
        return {f"alpha{i + 1}": a.detach() for i, a in enumerate(self.alphas)}
