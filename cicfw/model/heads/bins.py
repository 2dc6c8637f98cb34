"""Steering discretisation shared by the classification heads: 9 bins of 0.2 on [-0.9, 0.9]."""
from __future__ import annotations

import torch

from cicfw.core.errors import CicfwError


class SteeringBins:
    """``n`` equal bins over [low, high]; the paper uses 9 bins of width 0.2, midpoints -0.8..0.8.

    Bin i is ``(e_i, e_{i+1}]``: a steer exactly on an inner edge belongs to the bin on its left
    (the lower steering), in every float dtype (-0.1 is class 3 and 0.1 class 4 for the paper's bins).
    Values outside the range fall into the end bins (training drops |steer| > 0.8 anyway).
    """

    def __init__(self, n: int = 9, low: float = -0.9, high: float = 0.9) -> None:
        if n < 2:
            raise CicfwError(f"the number of steering classes must be >= 2, got {n}")
        if not low < high:
            raise CicfwError(f"bin range needs low < high, got low={low}, high={high}")
        self.n = n
        self.low, self.high = float(low), float(high)
        width = (self.high - self.low) / n
        # Edges in float64, rounded to 12 decimals so that an edge written as a decimal (-0.1, 0.7)
        # is the very float a steer written the same way becomes; to_class rounds them to the
        # steer's dtype. (torch.linspace in float32 puts -0.1's edge one ulp below -0.1, which sent
        # a steer of exactly -0.1 to the right-hand bin while every other edge went left.)
        self._edges64 = torch.tensor([round(self.low + k * width, 12) for k in range(n + 1)], dtype=torch.float64)
        self.edges = self._edges64.float()
        self.midpoints = torch.tensor(
            [round(self.low + (k + 0.5) * width, 12) for k in range(n)], dtype=torch.float64).float()

    def to_class(self, steer: torch.Tensor) -> torch.Tensor:
        """Bin index (B,) of each steer: ``e_i < steer <= e_{i+1}``, the end bins open outwards."""
        inner = self._edges64[1:-1].to(steer.device, steer.dtype)
        return torch.bucketize(steer.contiguous(), inner, right=False)

    def __repr__(self) -> str:
        return f"SteeringBins(n={self.n}, low={self.low}, high={self.high})"
