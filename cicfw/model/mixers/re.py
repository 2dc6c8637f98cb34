"""``re``: the paper's "fine tuning" co-learning, ``C = R ∘ E`` (Sec. "Specialist Branches Co-learning").

R is a hand-set binary 4x4 relationship matrix (a hyperparameter: which branch may use which);
E comes from a small dedicated MLP with a tanh output. As the paper keeps C's diagonal at 1:
``C = I + R ∘ offdiag(tanh(MLP(h)))``, ``A = C Â``. R's diagonal is therefore ignored.
"""
from __future__ import annotations

from typing import Sequence

import torch
from torch import nn

from cicfw import COMMANDS
from cicfw.core.errors import ConfigError
from cicfw.model.mixers.common import check_positive_int
from cicfw.model.mixers.gtu import CoLearningMixer, offdiag_mask
from cicfw.registry import MIXERS

# Every pair of branches related: the paper does not publish the R it tuned.
DEFAULT_R = [[0 if i == j else 1 for j in range(len(COMMANDS))] for i in range(len(COMMANDS))]


def check_relationship(R: Sequence[Sequence[int]], n: int) -> torch.Tensor:
    """R as a float (n, n) tensor, or one ValueError saying what is accepted."""
    accepted = (f"accepted: a {n}x{n} list of lists of 0/1 (rows and columns in branch order "
                f"{', '.join(COMMANDS)}; R[i][j] = 1 lets branch i use branch j's output)")
    try:
        rows = [list(r) for r in R]
        ok = len(rows) == n and all(len(r) == n for r in rows) and all(
            not isinstance(v, str) and v in (0, 1) for r in rows for v in r)
    except TypeError:
        ok = False
    if not ok:
        raise ConfigError("mixer.R", R, f"a binary {n}x{n} matrix",
                         f"mixer.R={R!r} is not a binary {n}x{n} matrix; {accepted}")
    return torch.tensor(rows, dtype=torch.float32)


@MIXERS.register("re")
class REMixer(CoLearningMixer):
    """CIL branches, then ``A = C Â`` with ``C = I + R ∘ offdiag(tanh(MLP(h)))``, R fixed and binary."""

    def __init__(
        self,
        in_dim: int,
        out_dim: int,
        R: Sequence[Sequence[int]] = DEFAULT_R,
        coef_hidden: int = 128,
        hidden: int = 256,
        dropout: float | Sequence[float] = (0.5, 0.0),
    ) -> None:
        n = self.n_branches
        r = check_relationship(R, n)
        super().__init__(in_dim, out_dim, hidden, dropout)  # the branches
        check_positive_int("coef_hidden", coef_hidden, "the width of the coefficient MLP")
        self.register_buffer("R", r)  # persistent: a checkpoint remembers its R
        # R's off-diagonal positions, row-major (an index, not a boolean mask: torch.compile traces it)
        self.register_buffer("_off", torch.nonzero(offdiag_mask(n).flatten()).flatten(), persistent=False)
        # E: the "dedicated neural network" of the paper, one tanh coefficient per off-diagonal entry.
        self.coef = nn.Sequential(nn.Linear(in_dim, coef_hidden), nn.ReLU(inplace=True),
                                  nn.Linear(coef_hidden, n * (n - 1)))

    def coefficients(self, h: torch.Tensor) -> torch.Tensor:
        r_off = self.R.flatten()[self._off]  # (n(n-1),), row-major like colearn
        return r_off * torch.tanh(self.coef(h))
