"""The Head contract: how the branch output encodes steering, its loss, and its decoding."""
from __future__ import annotations

import torch
from torch import nn


class Head(nn.Module):
    """Turns the selected branch output ``out`` (B, out_dim) into a loss and a steering value.

    Steering lives in [-1, 1]. Subclasses are built as ``cls(**kwargs_from_config)``, set
    ``out_dim`` in ``__init__`` and validate their kwargs there with a clear ``ValueError``.
    Classification heads also set ``self.bins`` (a ``SteeringBins``) and implement
    ``predict_class`` so the module can log bin accuracy.
    """

    out_dim: int
    bins = None  # a SteeringBins for classification heads

    def loss(self, out: torch.Tensor, steer: torch.Tensor) -> torch.Tensor:
        """Scalar training loss for outputs (B, out_dim) against steering targets (B,)."""
        raise NotImplementedError

    def decode(self, out: torch.Tensor) -> torch.Tensor:
        """Steering (B,) in [-1, 1] from outputs (B, out_dim)."""
        raise NotImplementedError

    def predict_class(self, out: torch.Tensor) -> torch.Tensor:
        """Predicted bin index (B,) for classification heads."""
        raise NotImplementedError(f"{type(self).__name__} is not a classification head")
