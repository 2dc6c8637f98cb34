"""Shared base of the classification heads: steering bins, softmax scores, and their decoding.

The paper's classes are 9 bins of width 0.2 on [-0.9, 0.9] (midpoints m = -0.8..0.8). The class
count, the range and the width are all kwargs, checked against each other so that overriding one of
them alone (``head.n_classes=11``) is an error and not a silent change of the bins.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from cicfw.core.config_checks import is_number
from cicfw.core.errors import ConfigError
from cicfw.model.heads.base import Head
from cicfw.model.heads.bins import SteeringBins

DECODERS = ("argmax", "expectation")


def make_bins(n_classes: object, low: object, high: object, bin_width: object | None) -> SteeringBins:
    """SteeringBins from the head's kwargs, or one ValueError naming the mismatch."""
    if isinstance(n_classes, bool) or not isinstance(n_classes, int) or n_classes < 2:
        raise ConfigError("head.n_classes", n_classes, "an integer >= 2",
                         f"head.n_classes={n_classes!r} is not valid; use an integer >= 2 (paper: 9)")
    if not (is_number(low) and is_number(high) and -1.0 <= low < high <= 1.0):
        raise ConfigError(
            "head.low", [low, high], "-1 <= low < high <= 1",
            f"head.low={low!r}, head.high={high!r} are not valid; need -1 <= low < high <= 1 "
            f"(paper: -0.9, 0.9)")
    if bin_width is not None:
        if not (is_number(bin_width) and bin_width > 0):
            raise ConfigError("head.bin_width", bin_width, "a number > 0 or null",
                             f"head.bin_width={bin_width!r} is not valid; use a number > 0 or null (paper: 0.2)")
        if not math.isclose(n_classes * bin_width, high - low, rel_tol=1e-6, abs_tol=1e-9):
            raise ConfigError(
                "head.n_classes", n_classes, "(high - low) / bin_width",
                f"head.n_classes={n_classes} does not match the bin edges: {n_classes} bins of width "
                f"{bin_width} span {n_classes * bin_width:g}, but [low, high] = [{low}, {high}] spans "
                f"{high - low:g}; accepted: n_classes = (high - low) / bin_width = {(high - low) / bin_width:g}, "
                f"or change bin_width / low / high with it (or set head.bin_width=null)")
    return SteeringBins(n_classes, low, high)


class BinnedHead(Head):
    """K = n_classes logits; ``O = softmax(out)``; classes are steering bins (``self.bins``)."""

    default_decode = "argmax"

    def __init__(
        self,
        n_classes: int = 9,
        low: float = -0.9,
        high: float = 0.9,
        bin_width: float | None = 0.2,
        decode: str | None = None,
    ) -> None:
        super().__init__()
        self.bins = make_bins(n_classes, low, high, bin_width)
        decode = decode or self.default_decode
        if decode not in DECODERS:
            raise ConfigError("head.decode", decode, f"one of {', '.join(DECODERS)}",
                             f"head.decode={decode!r} is not known; use one of {', '.join(DECODERS)}")
        self.decode_mode = decode
        self.out_dim = n_classes
        # Not persistent: derived from the kwargs, which the checkpoint's hyperparameters hold.
        self.register_buffer("midpoints", self.bins.midpoints.clone(), persistent=False)

    def scores(self, out: torch.Tensor) -> torch.Tensor:
        """Softmax class scores O (B, N)."""
        return torch.softmax(out, dim=-1)

    def expectation(self, out: torch.Tensor) -> torch.Tensor:
        """``Σ_i O_i m_i`` (B,): the score-weighted mean of the bin midpoints."""
        return self.scores(out) @ self.midpoints.to(out.dtype)

    def cross_entropy(self, out: torch.Tensor, steer: torch.Tensor) -> torch.Tensor:
        """``−Σ_i ȳ_i log O_i`` averaged over the batch, ȳ the one-hot bin of ``steer``."""
        return F.cross_entropy(out, self.bins.to_class(steer))

    def predict_class(self, out: torch.Tensor) -> torch.Tensor:
        return out.argmax(dim=-1)

    def decode(self, out: torch.Tensor) -> torch.Tensor:
        if self.decode_mode == "expectation":
            return self.expectation(out)
        return self.midpoints.to(out.dtype)[self.predict_class(out)]
