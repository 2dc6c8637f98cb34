"""Steering discretisation shared by the classification heads: 9 bins of 0.2 on [-0.9, 0.9]."""
from __future__ import annotations

import torch


class SteeringBins:
    """``n`` equal bins over [low, high]; the paper uses 9 bins of width 0.2, midpoints -0.8..0.8.

    Values outside the range fall into the end bins (training drops |steer| > 0.8 anyway).
    """

    def __init__(self, n: int = 9, low: float = -0.9, high: float = 0.9) -> None:
        if n < 2:
            raise ValueError(f"the number of steering classes must be >= 2, got {n}")
        if not low < high:
            raise ValueError(f"bin range needs low < high, got low={low}, high={high}")
        self.n = n
        self.low, self.high = float(low), float(high)
        self.edges = torch.linspace(low, high, n + 1)
        self.midpoints = (self.edges[:-1] + self.edges[1:]) / 2

    def to_class(self, steer: torch.Tensor) -> torch.Tensor:
        inner = self.edges[1:-1].to(steer.device, steer.dtype)
        return torch.bucketize(steer.contiguous(), inner, right=False)

    def __repr__(self) -> str:
        return f"SteeringBins(n={self.n}, low={self.low}, high={self.high})"
