"""``soft_sharing``: soft parameter sharing (Duong et al. 2015; the paper's Table 4 "Parameter soft sharing").

Each branch keeps its own parameters, as in CIL; the loss gets ``λ Σ_{i<j} ||θ_i − θ_j||²`` over
every pair of branches, pulling the branches towards each other instead of sharing one network.
"""
from __future__ import annotations

from typing import Sequence

import torch

from cicfw.core.config_checks import is_number
from cicfw.core.errors import ConfigError
from cicfw.model.mixers.independent import IndependentMixer
from cicfw.registry import MIXERS


@MIXERS.register("soft_sharing")
class SoftSharingMixer(IndependentMixer):
    """Four CIL branches; regularizer ``λ Σ_{i<j} ||θ_i − θ_j||²`` (all weights and biases of a branch)."""

    def __init__(self, in_dim: int, out_dim: int, lam: float = 1e-4, hidden: int = 256,
                 dropout: float | Sequence[float] = (0.5, 0.0)) -> None:
        if not (is_number(lam) and lam >= 0):  # finite: an inf weight makes the loss inf, the weights NaN
            raise ConfigError("mixer.lam", lam, "a finite number >= 0",
                             f"mixer.lam={lam!r} is not valid; the L2 weight λ must be a finite number >= 0")
        super().__init__(in_dim, out_dim, hidden, dropout)
        self.lam = float(lam)

    def distance(self) -> torch.Tensor:
        """``Σ_{i<j} ||θ_i − θ_j||²`` (unweighted)."""
        flat = torch.stack([torch.cat([p.reshape(-1) for p in b.parameters()]) for b in self.branches])  # (4, P)
        total = flat.new_zeros(())
        for i in range(len(flat)):
            for j in range(i + 1, len(flat)):
                total = total + (flat[i] - flat[j]).pow(2).sum()
        return total

    def regularizer(self) -> torch.Tensor:
        return self.lam * self.distance()
