"""``gtu``: conditional imitation co-learning (the paper's CIC, Sec. "Specialist Branches Co-learning").

Each branch computes its own output Â_k as in CIL; a per-sample co-learning matrix
``C = I + offdiag(tanh(W_a h) * sigmoid(W_g h))`` (gated tanh units, Dauphin et al. 2017) then
mixes them: ``A = C Â``. The gate lets the network switch a branch-to-branch link off per scene.
"""
from __future__ import annotations

from typing import Sequence

import torch
from torch import nn

from cicfw.model.mixers.independent import IndependentMixer
from cicfw.registry import MIXERS


def offdiag_mask(n: int) -> torch.Tensor:
    """Boolean (n, n) mask, True off the diagonal."""
    return ~torch.eye(n, dtype=torch.bool)


def offdiag(values: torch.Tensor, n: int) -> torch.Tensor:
    """The (..., n, n) matrices with ``values`` (..., n(n-1)) off the diagonal, row-major (c[i, j], i != j),
    and zeros on it. Built by padding, not boolean indexing, so torch.compile traces it in one graph:
    row-major, the n(n-1) off-diagonal entries come in n-1 runs of n, each run after one diagonal entry."""
    lead = values.shape[:-1]
    runs = values.reshape(*lead, n - 1, n)
    flat = torch.nn.functional.pad(runs, (1, 0)).reshape(*lead, (n - 1) * (n + 1))  # d0 o.. d1 o.. ...
    return torch.nn.functional.pad(flat, (0, 1)).reshape(*lead, n, n)  # ... and the last diagonal entry


def colearn(coefs: torch.Tensor, outputs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``C = I + offdiag(coefs)`` from per-sample off-diagonal coefficients (B, n(n-1)) and
    ``A = C Â`` for branch outputs Â (B, n, K). Returns (A, C)."""
    n = outputs.shape[1]
    c = torch.eye(n, dtype=outputs.dtype, device=outputs.device) + offdiag(coefs.to(outputs.dtype), n)
    return torch.bmm(c, outputs), c


class CoLearningMixer(IndependentMixer):
    """CIL branches (``independent``'s) mixed per sample by ``A = C Â``, ``C = I + offdiag(coefficients(h))``."""

    _c: torch.Tensor | None = None  # the last forward's C, for inspect()

    def coefficients(self, h: torch.Tensor) -> torch.Tensor:
        """The off-diagonal coefficients (B, n(n-1)) of C for features ``h``."""
        raise NotImplementedError

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        outputs = torch.stack([branch(h) for branch in self.branches], dim=1)
        mixed, c = colearn(self.coefficients(h), outputs)
        self._c = c.detach()  # for inspect(); detached so it does not hold the graph
        return mixed

    def inspect(self) -> dict[str, torch.Tensor]:
        return {} if self._c is None else {"C": self._c}


@MIXERS.register("gtu")
class GTUMixer(CoLearningMixer):
    """CIL branches, then ``A = C Â`` with ``C = I + offdiag(tanh(W_a h) * sigmoid(W_g h))`` per sample."""

    def __init__(self, in_dim: int, out_dim: int, hidden: int = 256,
                 dropout: float | Sequence[float] = (0.5, 0.0)) -> None:
        super().__init__(in_dim, out_dim, hidden, dropout)
        n = self.n_branches
        self.coef = nn.Linear(in_dim, n * (n - 1))  # W_a: the co-learning coefficient, tanh -> [-1, 1]
        self.gate = nn.Linear(in_dim, n * (n - 1))  # W_g: the gate, sigmoid -> [0, 1]

    def coefficients(self, h: torch.Tensor) -> torch.Tensor:
        return torch.tanh(self.coef(h)) * torch.sigmoid(self.gate(h))
