"""The Mixer contract: what every branch mixer (built-in or plugin) provides."""
from __future__ import annotations

import torch
from torch import nn

from cicfw import N_COMMANDS


class Mixer(nn.Module):
    """Owns the command branches: maps shared features ``h`` (B, in_dim) to (B, 4, out_dim).

    The contract every mixer keeps, built-in or plugin (``cicfw.testing.check_mixer`` checks it):

    - **Construction.** ``cls(in_dim=..., out_dim=..., **kwargs)`` where ``in_dim`` is the
      encoder's width, ``out_dim`` the head's K, and ``kwargs`` the config node ``mixer/<name>.yaml``
      minus its ``name:`` key: plain data only (numbers, strings, lists), since checkpoints store
      them and rebuild the mixer from them. Validate them here with one ``ValueError`` that names
      the key and what is accepted (``mixer.hidden=0 is not valid; use a positive integer``),
      never a shape error at the first step.
    - **forward(h) -> (B, 4, out_dim).** Branch order is [follow, left, right, straight] (CIL
      command code - 2). The module picks ``out[b, command[b]]``, so a mixer never sees the
      command. Each sample's output depends on that sample only (no mixing across the batch in
      eval mode).
    - **Every parameter gets a gradient** from the loss in every step (DDP's default fails
      otherwise); a part used only sometimes must still take part in the graph.
    - **regularizer() -> scalar tensor**, already weighted, added to the training loss; zero
      unless the method has one.
    - **inspect() -> {name: tensor}** from the last forward, for the diagnostics heatmaps: (B, r, c)
      per sample (averaged per command) or (r, c) global. Optional.
    - **kept_on_resume**: the kwargs whose other value would give the same-shaped weights another meaning
      (an attention's number of heads): resuming a checkpoint with another value is refused. Optional.
    - **Registration.** Built-ins: ``@MIXERS.register("name")``. Plugins: an entry point in the
      group ``cicfw.mixers`` (``name = package.module:Class``) and a config ``mixer/<name>.yaml``
      on Hydra's search path (a SearchPathPlugin); see docs/plugins.md. Names are unique.
    """

    n_branches: int = N_COMMANDS
    kept_on_resume: tuple[str, ...] = ()

    def __init__(self, in_dim: int, out_dim: int) -> None:
        super().__init__()
        self.in_dim = in_dim
        self.out_dim = out_dim

    def forward(self, h: torch.Tensor) -> torch.Tensor:  # (B, in_dim) -> (B, 4, out_dim)
        raise NotImplementedError

    def regularizer(self) -> torch.Tensor:
        """A scalar added to the loss (already weighted); zero unless the method has one."""
        return next(self.parameters()).new_zeros(())

    def inspect(self) -> dict[str, torch.Tensor]:
        """Matrices worth looking at from the last forward, for logging.

        A value shaped (B, r, c) is per sample (the logger averages it per command);
        a value shaped (r, c) is global (e.g. learned cross-stitch alphas). Empty by default.
        """
        return {}
