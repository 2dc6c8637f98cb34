"""``coexistence``: classification with the co-existence probability loss (the paper's Sec.
"Co-existence Probability Based Loss", Eq. 4, after Ding et al.; Table 3, best W = 0.6).

``l = −(1−W) Σ_i ȳ_i log O_i − W Oᵀ μ O`` with a Gaussian ``μ_ij = exp(−(i−j)² / 2σ²)`` over class
indices (σ² = 1): scores are pulled towards neighbouring classes, so a miss lands near the target.
"""
from __future__ import annotations

import torch

from cicfw.core.errors import ConfigError
from cicfw.core.config_checks import is_number
from cicfw.model.heads.binned import BinnedHead
from cicfw.registry import HEADS


def gaussian_coexistence(n: int, sigma2: float) -> torch.Tensor:
    """μ (n, n): ``exp(−(i−j)² / 2σ²)``; symmetric, ones on the diagonal."""
    idx = torch.arange(n, dtype=torch.float64)
    return torch.exp(-((idx[:, None] - idx[None, :]) ** 2) / (2.0 * sigma2)).float()


@HEADS.register("coexistence")
class CoexistenceHead(BinnedHead):
    """−(1−W)·CCE − W·Oᵀ μ O; decode the argmax midpoint (or the expectation)."""

    def __init__(self, W: float = 0.6, sigma2: float = 1.0, **bins_kwargs) -> None:
        if not (is_number(W) and 0.0 < W < 1.0):
            raise ConfigError("head.W", W, "a number in (0, 1)",
                             f"head.W={W!r} is not valid; the co-existence weight must be in the open interval "
                             f"(0, 1) (paper: 0.4, 0.6, 0.8; best 0.6)")
        if not (is_number(sigma2) and sigma2 > 0):
            raise ConfigError("head.sigma2", sigma2, "a finite number > 0",
                             f"head.sigma2={sigma2!r} is not valid; the Gaussian's variance must be a finite number > 0 "
                             f"(paper: 1)")
        super().__init__(**bins_kwargs)
        self.W, self.sigma2 = float(W), float(sigma2)
        self.register_buffer("mu", gaussian_coexistence(self.bins.n, self.sigma2), persistent=False)

    def coexistence(self, out: torch.Tensor) -> torch.Tensor:
        """``Oᵀ μ O`` per sample (B,)."""
        o = self.scores(out)
        return ((o @ self.mu.to(o.dtype)) * o).sum(dim=-1)

    def loss(self, out: torch.Tensor, steer: torch.Tensor) -> torch.Tensor:
        return (1.0 - self.W) * self.cross_entropy(out, steer) - self.W * self.coexistence(out).mean()
