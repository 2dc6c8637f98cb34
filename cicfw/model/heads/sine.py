"""``sine``: sine-wave encoding of the steering (the paper's Table 4 "Sine wave encoding", after Eraqi
et al.'s arbitrary-function encoding, cited as [sine] in the paper).

The target is one period of a sine wave sampled on N output units, phase-shifted by the steering:
``t_n = sin(2π n / N + φ)``, ``φ = steer · phase_range · π``. Loss: MSE between the N outputs and t.
Decode: project the outputs on sin and cos (``φ̂ = atan2(Σ o_n cos x_n, Σ o_n sin x_n)``, exact for
N >= 3) and divide by ``phase_range · π``. ``phase_range < 1`` keeps steer = ±1 at distinct phases,
so the mapping is invertible on [-1, 1].
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from cicfw.core.errors import ConfigError
from cicfw.model.heads.base import Head
from cicfw.registry import HEADS


@HEADS.register("sine")
class SineHead(Head):
    """N units carry ``sin(2πn/N + steer·phase_range·π)``; MSE; decode the phase by projection."""

    def __init__(self, n_units: int = 61, phase_range: float = 0.9) -> None:
        super().__init__()
        if isinstance(n_units, bool) or not isinstance(n_units, int) or n_units < 3:
            raise ConfigError("head.n_units", n_units, "an integer >= 3",
                             f"head.n_units={n_units!r} is not valid; use an integer N >= 3 (a wave sampled on "
                             f"fewer points cannot be projected on sin and cos; paper tried 21, 61, 101, 141)")
        if isinstance(phase_range, bool) or not isinstance(phase_range, (int, float)) or not 0 < phase_range < 1:
            raise ConfigError("head.phase_range", phase_range, "a number in (0, 1)",
                             f"head.phase_range={phase_range!r} is not valid; use a number in (0, 1): the largest "
                             f"phase as a fraction of π (1 would map steer -1 and +1 to the same wave)")
        self.out_dim = n_units
        self.max_phase = float(phase_range) * math.pi
        x = 2.0 * math.pi * torch.arange(n_units, dtype=torch.float64) / n_units
        self.register_buffer("sin_x", torch.sin(x).float(), persistent=False)
        self.register_buffer("cos_x", torch.cos(x).float(), persistent=False)

    def encode(self, steer: torch.Tensor) -> torch.Tensor:
        """The target wave (B, N) for steering (B,): ``sin(x + φ) = sin x cos φ + cos x sin φ``."""
        phase = steer.to(self.sin_x.dtype)[:, None] * self.max_phase
        return self.sin_x * torch.cos(phase) + self.cos_x * torch.sin(phase)

    def loss(self, out: torch.Tensor, steer: torch.Tensor) -> torch.Tensor:
        return F.mse_loss(out, self.encode(steer).to(out.dtype))

    def decode(self, out: torch.Tensor) -> torch.Tensor:
        # Σ t_n sin x_n = (N/2) cos φ and Σ t_n cos x_n = (N/2) sin φ for N >= 3 (discrete orthogonality).
        phase = torch.atan2(out @ self.cos_x.to(out.dtype), out @ self.sin_x.to(out.dtype))
        return (phase / self.max_phase).clamp(-1.0, 1.0)
