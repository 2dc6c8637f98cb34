"""``softmax``: steering as classification (the paper's "Classification", after DEX, Rothe et al. 2015).

K = 9 bins of width 0.2 (midpoints -0.8..0.8); loss = categorical cross-entropy on the bin of the
target; decode = the midpoint of the argmax bin, or the expectation Σ O_i m_i (``decode``).
"""
from __future__ import annotations

import torch

from cicfw.model.heads.binned import BinnedHead
from cicfw.registry import HEADS


@HEADS.register("softmax")
class SoftmaxHead(BinnedHead):
    """CCE on the steering bin; decode the argmax bin's midpoint (or the expectation)."""

    def loss(self, out: torch.Tensor, steer: torch.Tensor) -> torch.Tensor:
        return self.cross_entropy(out, steer)
