"""The Head contract: how the branch output encodes steering, its loss, and its decoding."""
from __future__ import annotations

import torch
from torch import nn


class Head(nn.Module):
    """Turns the selected branch output ``out`` (B, out_dim) into a loss and a steering value.

    The contract every head keeps, built-in or plugin (``cicfw.testing.check_head`` checks it):

    - **Construction.** ``cls(**kwargs)``, ``kwargs`` being the config node ``head/<name>.yaml``
      minus its ``name:`` key (plain data: checkpoints rebuild the head from them). ``__init__``
      sets ``self.out_dim`` (K, a positive int: the mixer is built with it) and validates the
      kwargs with one ``ValueError`` that names the key and what is accepted.
    - **loss(out, steer) -> scalar tensor**, differentiable, for outputs (B, K) and steering
      targets (B,) in [-1, 1].
    - **decode(out) -> steering (B,)** in [-1, 1]; used for the metrics and for driving.
    - **Classification heads** also set ``self.bins`` (a ``SteeringBins``) and implement
      ``predict_class(out) -> (B,)`` integer bins, so the module logs bin accuracy.
    - **Registration.** Built-ins: ``@HEADS.register("name")``. Plugins: an entry point in the
      group ``cicfw.heads`` and a config ``head/<name>.yaml`` on Hydra's search path; see
      docs/plugins.md.
    """

    out_dim: int
    bins = None  # a SteeringBins for classification heads
    kept_on_resume: tuple[str, ...] = ()  # kwargs a resume must keep: the outputs would mean something else

    def loss(self, out: torch.Tensor, steer: torch.Tensor) -> torch.Tensor:
        """Scalar training loss for outputs (B, out_dim) against steering targets (B,)."""
        raise NotImplementedError

    def decode(self, out: torch.Tensor) -> torch.Tensor:
        """Steering (B,) in [-1, 1] from outputs (B, out_dim)."""
        raise NotImplementedError

    def predict_class(self, out: torch.Tensor) -> torch.Tensor:
        """Predicted bin index (B,) for classification heads."""
        raise NotImplementedError(f"{type(self).__name__} is not a classification head")
