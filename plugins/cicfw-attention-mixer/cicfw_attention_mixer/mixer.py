"""``attention``: command branches that attend to each other's hidden states.

Each of the four branches maps the shared features ``h`` to its own hidden state, as the first two
layers of a CIL branch do. The four hidden states are four tokens of one multi-head self-attention
layer (plus a learned branch embedding, so a token knows which command it speaks for): each branch
reads what the others computed. A per-branch gate ``tanh(g_k)`` scales what branch k adds from that
read (a gated residual); with ``g = 0`` at the start the mixer is exactly CIL's independent branches
and learns how much to share. Each branch's own output layer then gives K outputs.

Unlike ``gtu``/``re`` (which mix the branch *outputs* with a 4x4 matrix) this mixes *hidden states*,
with per-sample, content-dependent weights; ``inspect()`` exposes them for the heatmaps.
"""
from __future__ import annotations

import math

import torch
from torch import nn

from cicfw.model.mixers import Mixer


def _check(ok: bool, key: str, value: object, accepted: str) -> None:
    if not ok:
        raise ValueError(f"mixer.{key}={value!r} is not valid for the attention mixer; use {accepted}")


def _is_int(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_prob(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and 0.0 <= value < 1.0


class AttentionMixer(Mixer):
    """Branch hidden states (B, 4, hidden) -> self-attention across branches -> gated residual ->
    per-branch output layers (B, 4, K)."""

    kept_on_resume = ("heads",)  # the same weights split into other heads attend otherwise

    def __init__(
        self,
        in_dim: int,
        out_dim: int,
        hidden: int = 256,
        heads: int = 4,
        dropout: float = 0.5,
        attn_dropout: float = 0.0,
        gate_init: float = 0.0,
    ) -> None:
        super().__init__(in_dim, out_dim)
        _check(_is_int(hidden) and hidden >= 1, "hidden", hidden, "a positive integer (CIL: 256)")
        _check(_is_int(heads) and heads >= 1, "heads", heads, "a positive integer")
        _check(hidden % heads == 0, "heads", heads, f"a divisor of mixer.hidden={hidden}")
        _check(_is_prob(dropout), "dropout", dropout, "a probability in [0, 1) (CIL: 0.5)")
        _check(_is_prob(attn_dropout), "attn_dropout", attn_dropout, "a probability in [0, 1)")
        _check(isinstance(gate_init, (int, float)) and not isinstance(gate_init, bool) and math.isfinite(gate_init),
               "gate_init", gate_init, "a finite number (0 starts as independent branches)")
        n = self.n_branches
        self.branches = nn.ModuleList(
            nn.Sequential(
                nn.Linear(in_dim, hidden), nn.ReLU(inplace=True), nn.Dropout(dropout),
                nn.Linear(hidden, hidden), nn.ReLU(inplace=True), nn.Dropout(dropout),
            )
            for _ in range(n)
        )
        self.branch_embedding = nn.Parameter(torch.randn(n, hidden) * 0.02)
        self.norm = nn.LayerNorm(hidden)
        self.attention = nn.MultiheadAttention(hidden, heads, dropout=attn_dropout, batch_first=True)
        self.gate = nn.Parameter(torch.full((n, 1), float(gate_init)))
        self.outputs = nn.ModuleList(nn.Linear(hidden, out_dim) for _ in range(n))
        self._weights: torch.Tensor | None = None

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        z = torch.stack([branch(h) for branch in self.branches], dim=1)  # (B, 4, hidden)
        q = self.norm(z + self.branch_embedding)  # pre-norm tokens, tagged with their branch
        read, weights = self.attention(q, q, q, need_weights=True, average_attn_weights=True)
        z = z + torch.tanh(self.gate) * read  # gate (4, 1) broadcasts over batch and features
        self._weights = weights  # (B, 4, 4): row i = how much branch i reads from each branch j
        return torch.stack([out(z[:, i]) for i, out in enumerate(self.outputs)], dim=1)

    def inspect(self) -> dict[str, torch.Tensor]:
        if self._weights is None:
            return {}
        return {"attention": self._weights.detach(), "gate": torch.tanh(self.gate).detach()}
