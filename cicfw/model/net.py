"""SteeringNet: encoder -> branch mixer -> head, the driving function as a plain ``nn.Module``.

Everything that drives (evaluation, export, the Agent, diagnose) needs only this; training wraps it in
``CICModule`` (cicfw/model/module.py), which adds the optimizer and metrics and is the only part that
imports Lightning. Both hold the parts as ``encoder``, ``mixer``, ``head``, so a training checkpoint's
``state_dict`` loads into either.

Batches are dicts: ``image`` uint8 (B, 3, 88, 200), ``speed`` km/h (B,), ``command`` branch index
(B,) in 0..3 (= CIL code - 2, order ``cicfw.COMMANDS``), ``steer`` (B,) in [-1, 1].
"""
from __future__ import annotations

import inspect
from typing import Any, Mapping

import torch
from torch import nn

from cicfw.core.config_checks import is_number
from cicfw.core.errors import ConfigError
from cicfw.registry import ENCODERS, HEADS, MIXERS


#: each part's registry, by its hyper-parameter's name
PART_REGISTRIES = {"encoder": ENCODERS, "head": HEADS, "mixer": MIXERS}


def build_part(part: str, name: str, kwargs: Mapping[str, Any] | None,
               widths: tuple[int, int] | None = None) -> nn.Module:
    """The registered ``part`` called ``name``, built with ``kwargs``; a mixer between the encoder's and the head's
    widths (``widths``: in, out), which ``SteeringNet`` gives it (a kwarg naming them again is a TypeError)."""
    cls, kwargs = PART_REGISTRIES[part].get(name), dict(kwargs or {})
    if widths is None:
        return cls(**kwargs)
    twice = sorted({"in_dim", "out_dim"} & set(kwargs))
    if twice:  # said here: the call's own TypeError comes out as a KeyError when built inside an except block
        raise TypeError(f"{cls.__name__}() got multiple values for keyword argument '{twice[0]}'")
    return cls(in_dim=widths[0], out_dim=widths[1], **kwargs)


class SteeringNet(nn.Module):
    """The agent: one encoder pass, every branch's output through the mixer, decoded by the head."""

    def __init__(
        self,
        encoder: str = "cil",
        encoder_kwargs: Mapping[str, Any] | None = None,
        mixer: str = "independent",
        mixer_kwargs: Mapping[str, Any] | None = None,
        head: str = "regression",
        head_kwargs: Mapping[str, Any] | None = None,
        speed_norm_kmh: float = 40.0,
    ) -> None:
        super().__init__()
        if not (is_number(speed_norm_kmh) and speed_norm_kmh > 0):
            raise ConfigError("model.speed_norm_kmh", speed_norm_kmh, "a number > 0")
        self.encoder = build_part("encoder", encoder, encoder_kwargs)
        self.head = build_part("head", head, head_kwargs)
        self.mixer = build_part("mixer", mixer, mixer_kwargs, (self.encoder.out_dim, self.head.out_dim))
        self.speed_norm_kmh = speed_norm_kmh
        self.channels_last = False

    def use_channels_last(self) -> "SteeringNet":
        """NHWC layout for the encoder's convolutions (a speed switch; outputs are unchanged)."""
        self.channels_last = True
        return self.to(memory_format=torch.channels_last)

    def branch_outputs(self, image: torch.Tensor, speed_kmh: torch.Tensor) -> torch.Tensor:
        """All four branches' outputs (B, 4, K)."""
        if self.channels_last:
            image = image.contiguous(memory_format=torch.channels_last)
        h = self.encoder(image, speed_kmh.float() / self.speed_norm_kmh)
        return self.mixer(h)

    def forward(self, image: torch.Tensor, speed_kmh: torch.Tensor, command: torch.Tensor) -> torch.Tensor:
        """The output (B, K) of each sample's own branch: ``out[b, command[b]]``."""
        out = self.branch_outputs(image, speed_kmh)
        return out[torch.arange(out.shape[0], device=out.device), command.long()]

    @torch.no_grad()
    def predict_steer(self, image: torch.Tensor, speed_kmh: torch.Tensor, command: torch.Tensor) -> torch.Tensor:
        """Steering (B,) in [-1, 1]; ``command`` is the branch index (CIL code - 2)."""
        return self.head.decode(self(image, speed_kmh, command))


#: the hyper-parameters that build the network, with their defaults; a checkpoint's others are training's
NET_DEFAULTS: dict[str, Any] = {name: p.default for name, p in inspect.signature(SteeringNet.__init__).parameters.items()
                                if name != "self"}
NET_KEYS = tuple(NET_DEFAULTS)
