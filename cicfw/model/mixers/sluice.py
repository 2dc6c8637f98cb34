"""``sluice``: sluice networks (Ruder et al. 2019, "Latent multi-task architecture learning"; the
paper's Table 4 "Sluice network").

Each branch's hidden layers are split into S subspaces (S = 2: meant as one shared, one
branch-specific). After each hidden layer a learned α ((4S)x(4S)) mixes every (branch, subspace)
unit with every other: ``x'_{k,s} = Σ_{j,t} α_{(k,s),(j,t)} x_{j,t}``. A learned β (4 x layers)
combines each branch's hidden layers before its output layer: ``z_k = Σ_l β_{k,l} x'^l_k``.
Regularizer: ``ortho · Σ_k Σ_l Σ_{s<t} ||W^l_{k,s} W^l_{k,t}ᵀ||_F²``, where W^l_{k,s} are the rows of
branch k's layer-l weight that produce subspace s, so the subspaces read orthogonal directions.
With α = I and β = (0, ..., 0, 1) this is exactly ``independent``.
"""
from __future__ import annotations

from typing import Sequence

import torch
from torch import nn

from cicfw.core.config_checks import is_number
from cicfw.core.errors import ConfigError
from cicfw.model.mixers.common import check_positive_int, check_unit_interval
from cicfw.model.mixers.cross_stitch import HIDDEN_BLOCKS, OUTPUT_LAYER, run_block, stitch_init
from cicfw.model.mixers.independent import IndependentMixer
from cicfw.registry import MIXERS


@MIXERS.register("sluice")
class SluiceMixer(IndependentMixer):
    """CIL branches with subspace-split hidden layers, learned α (units across branches), β (over layers)."""

    def __init__(
        self,
        in_dim: int,
        out_dim: int,
        subspaces: int = 2,
        alpha_diag: float = 0.9,
        beta_last: float = 0.9,
        ortho: float = 1e-3,
        hidden: int = 256,
        dropout: float | Sequence[float] = (0.5, 0.0),
    ) -> None:
        super().__init__(in_dim, out_dim, hidden, dropout)  # the branches
        check_positive_int("subspaces", subspaces, "the number of subspaces per hidden layer (paper: 2)")
        if subspaces < 2 or hidden % subspaces:
            raise ConfigError(
                "mixer.subspaces", subspaces, "an integer >= 2 that divides mixer.hidden",
                f"mixer.subspaces={subspaces!r} is not valid with mixer.hidden={hidden}; use an integer >= 2 "
                f"that divides the hidden width (paper: 2)")
        check_unit_interval("alpha_diag", alpha_diag, "the initial self-weight of each (branch, subspace)")
        check_unit_interval("beta_last", beta_last, "the initial weight of the last hidden layer in β")
        if not (is_number(ortho) and ortho >= 0):  # nan and inf too: either turns every weight NaN
            raise ConfigError("mixer.ortho", ortho, "a finite number >= 0",
                             f"mixer.ortho={ortho!r} is not valid; the orthogonality weight must be a finite number >= 0")
        n, layers = self.n_branches, len(HIDDEN_BLOCKS)
        self.subspaces, self.ortho = subspaces, float(ortho)
        self.alphas = nn.ParameterList(nn.Parameter(stitch_init(n * subspaces, alpha_diag)) for _ in HIDDEN_BLOCKS)
        beta = torch.full((n, layers), (1.0 - beta_last) / (layers - 1))  # Ruder et al.'s "imbalanced" init
        beta[:, -1] = beta_last
        self.beta = nn.Parameter(beta)

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        b, n, s = h.shape[0], self.n_branches, self.subspaces
        x = h[:, None].expand(-1, n, -1)
        layer_outputs = []
        for block, alpha in zip(HIDDEN_BLOCKS, self.alphas):
            y = run_block(self.branches, block, x)  # (B, n, H)
            units = y.reshape(b, n * s, -1)  # (B, n*S, H/S): unit (k, s) = branch k, subspace s
            x = torch.einsum("ij,bjd->bid", alpha, units).reshape(b, n, -1)
            layer_outputs.append(x)
        z = torch.einsum("kl,lbkd->bkd", self.beta, torch.stack(layer_outputs))
        return torch.stack([br[OUTPUT_LAYER](z[:, k]) for k, br in enumerate(self.branches)], dim=1)

    def orthogonality(self) -> torch.Tensor:
        """``Σ_k Σ_l Σ_{s<t} ||W_{k,s} W_{k,t}ᵀ||_F²`` over the branches' hidden weights (unweighted)."""
        total = self.beta.new_zeros(())
        for branch in self.branches:
            for block in HIDDEN_BLOCKS:
                parts = branch[block][0].weight.chunk(self.subspaces, dim=0)
                for i in range(len(parts)):
                    for j in range(i + 1, len(parts)):
                        total = total + (parts[i] @ parts[j].T).pow(2).sum()
        return total

    def regularizer(self) -> torch.Tensor:
        return self.ortho * self.orthogonality()

    def inspect(self) -> dict[str, torch.Tensor]:
        out = {f"alpha{i + 1}": a.detach() for i, a in enumerate(self.alphas)}
        out["beta"] = self.beta.detach()
        return out
