"""``moe``: a multi-gate mixture-of-experts layer before the branches (MMoE, Ma et al. 2018).

The paper (Sec. "Specialist Branches Co-learning", Table 4 "Mixture of experts") adds "a gated
mixture of experts layer before splitting the network into specialist branches". Here: E expert
MLPs (in_dim -> expert_dim, ReLU) on the shared features h; each branch k has its own softmax gate
``g_k = softmax(W_k h)`` over the experts and reads ``x_k = Σ_e g_k,e expert_e(h)``, then runs a CIL
branch MLP ``expert_dim -> hidden -> hidden -> K``.
"""
from __future__ import annotations

from typing import Sequence

import torch
from torch import nn

from cicfw.model.mixers.base import Mixer
from cicfw.model.mixers.common import check_branch_kwargs, check_positive_int
from cicfw.model.mixers.independent import branch_mlp
from cicfw.registry import MIXERS


@MIXERS.register("moe")
class MoEMixer(Mixer):
    """E experts on h, one softmax gate per branch (MMoE), then a CIL branch MLP per command."""

    def __init__(
        self,
        in_dim: int,
        out_dim: int,
        experts: int = 4,
        expert_dim: int = 512,
        hidden: int = 256,
        dropout: float | Sequence[float] = (0.5, 0.0),
    ) -> None:
        super().__init__(in_dim, out_dim)
        check_positive_int("experts", experts, "the number of experts E (E >= 1)")
        check_positive_int("expert_dim", expert_dim, "the width of each expert's output")
        check_branch_kwargs(hidden, dropout)
        n = self.n_branches
        self.n_experts = experts
        # All experts as one wide layer: one matmul instead of E small ones (same maths).
        self.experts = nn.Sequential(nn.Linear(in_dim, experts * expert_dim), nn.ReLU(inplace=True))
        self.gates = nn.Linear(in_dim, n * experts)  # one gate per branch, each over the E experts
        self.branches = nn.ModuleList(branch_mlp(expert_dim, hidden, out_dim, dropout) for _ in range(n))
        self._gates: torch.Tensor | None = None

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        b = h.shape[0]
        experts = self.experts(h).view(b, self.n_experts, -1)  # (B, E, D)
        gates = torch.softmax(self.gates(h).view(b, self.n_branches, self.n_experts), dim=-1)  # (B, 4, E)
        inputs = torch.bmm(gates, experts)  # (B, 4, D): branch k reads Σ_e g_ke expert_e
        self._gates = gates.detach()  # for inspect()
        return torch.stack([branch(inputs[:, k]) for k, branch in enumerate(self.branches)], dim=1)

    def inspect(self) -> dict[str, torch.Tensor]:
        return {} if self._gates is None else {"gates": self._gates}
