"""Image + speed encoders; ``cil`` is the CIL perception stack (Codevilla et al. 2018)."""
from __future__ import annotations

import torch
from torch import nn

from cicfw.core.errors import ConfigError
from cicfw.registry import ENCODERS

IMAGE_HW = (88, 200)

# (out_channels, kernel, stride) of CIL's eight conv layers, no padding.
CIL_CONVS = ((32, 5, 2), (32, 3, 1), (64, 3, 2), (64, 3, 1), (128, 3, 2), (128, 3, 1), (256, 3, 1), (256, 3, 1))


def conv_out_hw(hw: tuple[int, int]) -> tuple[int, int]:
    """The (height, width) CIL's unpadded convolutions leave of an image of ``hw``: each takes ``(n - k) // s + 1``."""
    h, w = hw
    for _, k, s in CIL_CONVS:
        h, w = (h - k) // s + 1, (w - k) // s + 1
    return h, w


class Encoder(nn.Module):
    """Contract: ``forward(image uint8 (B, 3, 88, 200), speed (B,) normalised) -> h (B, out_dim)``."""

    out_dim: int


def _fc(i: int, o: int, dropout: float) -> nn.Sequential:
    return nn.Sequential(nn.Linear(i, o), nn.ReLU(inplace=True), nn.Dropout(dropout))


@ENCODERS.register("cil")
class CILEncoder(Encoder):
    """8 conv (BN, ReLU) -> 8192 -> FC 512 -> FC 512; speed FC 128 -> 128; concat -> FC 512.

    Dropout defaults follow the CIL authors' released network (carla-simulator/imitation-learning,
    ``dropout_vec``): none after the convolutions, 0.3 after the image FCs, 0.5 after the speed FCs
    and after the join. ``dropout_fc`` (one rate for every FC, cicfw 0.1's layout with
    ``dropout_conv=0.2, dropout_fc=0.5``) overrides the three FC rates when given.
    """

    def __init__(self, dropout_conv: float = 0.0, dropout_image_fc: float = 0.3, dropout_speed_fc: float = 0.5,
                 dropout_join: float = 0.5, dropout_fc: float | None = None, out_dim: int = 512) -> None:
        super().__init__()
        if dropout_fc is not None:
            dropout_image_fc = dropout_speed_fc = dropout_join = dropout_fc
        rates = {"dropout_conv": dropout_conv, "dropout_image_fc": dropout_image_fc,
                 "dropout_speed_fc": dropout_speed_fc, "dropout_join": dropout_join}
        for name, p in rates.items():
            if isinstance(p, bool) or not isinstance(p, (int, float)) or not 0 <= p < 1:
                raise ConfigError(f"encoder.{name}", p, "a probability in [0, 1)",
                                 f"encoder.{name}={p!r} is not valid; use a probability in [0, 1)")
        layers: list[nn.Module] = []
        c_in = 3
        for c_out, k, s in CIL_CONVS:
            layers += [nn.Conv2d(c_in, c_out, k, s, bias=False), nn.BatchNorm2d(c_out), nn.ReLU(inplace=True)]
            if dropout_conv:
                layers.append(nn.Dropout2d(dropout_conv))
            c_in = c_out
        self.convs = nn.Sequential(*layers)
        flat = c_in * conv_out_hw(IMAGE_HW)[0] * conv_out_hw(IMAGE_HW)[1]  # 256 x 2 x 16 = 8192
        self.image_fc = nn.Sequential(_fc(flat, 512, dropout_image_fc), _fc(512, 512, dropout_image_fc))
        self.speed_fc = nn.Sequential(_fc(1, 128, dropout_speed_fc), _fc(128, 128, dropout_speed_fc))
        self.join = _fc(512 + 128, out_dim, dropout_join)
        self.out_dim = out_dim

    def forward(self, image: torch.Tensor, speed: torch.Tensor) -> torch.Tensor:
        x = image.float() / 255.0  # pixels /255, as CIL
        x = self.convs(x).flatten(1)
        return self.join(torch.cat([self.image_fc(x), self.speed_fc(speed[:, None])], dim=1))
