"""``hybrid``: the paper's classification-regression hybrid loss (Sec. "Classification-Regression
Hybrid Loss", Eq. 3; Table 2, best W = 10).

``l = −Σ_i ȳ_i log O_i + W (y − ŷ)²`` with ``ŷ = Σ_i O_i m_i``: the cross-entropy gives a coarse bin,
the squared error on the expectation refines it. Decode: the expectation ŷ.
"""
from __future__ import annotations

import torch

from cicfw.core.errors import ConfigError
from cicfw.core.config_checks import is_number
from cicfw.model.heads.binned import BinnedHead
from cicfw.registry import HEADS


@HEADS.register("hybrid")
class HybridHead(BinnedHead):
    """CCE + W·(y − Σ O_i m_i)²; decode the expectation (or the argmax midpoint)."""

    default_decode = "expectation"

    def __init__(self, W: float = 10.0, **bins_kwargs) -> None:
        if not (is_number(W) and W >= 0):
            raise ConfigError("head.W", W, "a finite number >= 0",
                             f"head.W={W!r} is not valid; the weight of the squared term must be a finite number >= 0 "
                             f"(paper: 5, 10, 15; best 10)")
        super().__init__(**bins_kwargs)
        self.W = float(W)

    def squared_error(self, out: torch.Tensor, steer: torch.Tensor) -> torch.Tensor:
        """``(y − Σ_i O_i m_i)²`` averaged over the batch."""
        return (steer.to(out.dtype) - self.expectation(out)).pow(2).mean()

    def loss(self, out: torch.Tensor, steer: torch.Tensor) -> torch.Tensor:
        return self.cross_entropy(out, steer) + self.W * self.squared_error(out, steer)
