"""CIL's image augmentation set, applied per sample to a whole uint8 batch with OpenCV/numpy.

CIL (Codevilla et al. 2018) used Gaussian blur, additive Gaussian noise, pixel dropout, coarse
dropout, brightness add/multiply and contrast, each switched on per image with a probability.
The whole batch is handled in a few vectorised passes so augmentation costs ~1% of a training step.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import cv2
import numpy as np

from cicfw.core.config_checks import checked_probability, checked_range
from cicfw.core.errors import CicfwError


@dataclass
class AugmentConfig:
    """Probability and range of each CIL augmentation (the defaults are CIL's)."""

    p_blur: float = 0.09
    blur_sigma: tuple[float, float] = (0.0, 1.5)
    p_noise: float = 0.09
    noise_std: tuple[float, float] = (0.0, 0.05 * 255)
    p_dropout: float = 0.3
    dropout_fraction: tuple[float, float] = (0.0, 0.10)
    p_coarse_dropout: float = 0.3
    coarse_fraction: tuple[float, float] = (0.0, 0.10)
    coarse_size: tuple[float, float] = (0.08, 0.2)  # of the image side
    p_add: float = 0.3
    add: tuple[float, float] = (-20.0, 20.0)
    p_multiply: float = 0.4
    multiply: tuple[float, float] = (0.8, 1.2)
    p_contrast: float = 0.09
    contrast: tuple[float, float] = (0.8, 1.2)

    @classmethod
    def from_dict(cls, d: dict | None) -> "AugmentConfig":
        """The config from ``data.augment``'s overrides, every value checked by its key (a probability in
        [0, 1], a range ``[low, high]`` of numbers inside its domain) before any batch is augmented."""
        inf = float("inf")
        domains = {  # each range's (lowest, highest, the lowest allowed, in words)
            "blur_sigma": (0.0, inf, True, "a sigma >= 0 (pixels)"),
            "noise_std": (0.0, inf, True, "a standard deviation >= 0 (pixel levels)"),
            "dropout_fraction": (0.0, 1.0, True, "a fraction in [0, 1]"),
            "coarse_fraction": (0.0, 1.0, True, "a fraction in [0, 1]"),
            "coarse_size": (0.0, 1.0, False, "a size in (0, 1] of the image side"),
            "add": (-255.0, 255.0, True, "pixel levels in [-255, 255]"),
            "multiply": (0.0, inf, True, "a factor >= 0"),
            "contrast": (0.0, inf, True, "a factor >= 0"),
        }
        d = dict(d or {})
        known = {f.name for f in fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise CicfwError(f"unknown augmentation option(s) {sorted(unknown)}; accepted: {sorted(known)}",
                             key="data.augment", value=sorted(unknown))
        checked = {k: checked_probability(f"data.augment.{k}", v) if k.startswith("p_")
                   else checked_range(f"data.augment.{k}", v, *domains[k]) for k, v in d.items()}
        return cls(**checked)


def augment_batch(images: np.ndarray, cfg: AugmentConfig, rng: np.random.Generator) -> np.ndarray:
    """Augment uint8 images (B, H, W, 3) in place and return them."""
    b, h, w, _ = images.shape
    pick = lambda p: np.flatnonzero(rng.random(b) < p)  # noqa: E731 - indices of the samples hit

    for i in pick(cfg.p_blur):
        sigma = rng.uniform(*cfg.blur_sigma)
        if sigma > 0.1:
            cv2.GaussianBlur(images[i], (0, 0), sigma, dst=images[i])

    # Photometric ops chained in float32 on the affected images only.
    gain = np.ones(b, np.float32)
    bias = np.zeros(b, np.float32)
    idx = pick(cfg.p_multiply)
    gain[idx] = rng.uniform(*cfg.multiply, size=len(idx))
    idx = pick(cfg.p_add)
    bias[idx] = rng.uniform(*cfg.add, size=len(idx))
    contrast = np.ones(b, np.float32)
    idx = pick(cfg.p_contrast)
    contrast[idx] = rng.uniform(*cfg.contrast, size=len(idx))
    noisy = pick(cfg.p_noise)
    touched = np.flatnonzero((gain != 1) | (bias != 0) | (contrast != 1))
    touched = np.union1d(touched, noisy)
    if len(touched):
        x = images[touched].astype(np.float32)
        x = x * gain[touched, None, None, None] + bias[touched, None, None, None]
        c = contrast[touched, None, None, None]
        x = (x - 128.0) * c + 128.0
        hit = np.isin(touched, noisy)
        if hit.any():
            std = rng.uniform(*cfg.noise_std, size=int(hit.sum())).astype(np.float32)
            x[hit] += rng.standard_normal(x[hit].shape, dtype=np.float32) * std[:, None, None, None]
        images[touched] = np.clip(x, 0, 255).astype(np.uint8)

    for i in pick(cfg.p_dropout):
        mask = rng.random((h, w)) < rng.uniform(*cfg.dropout_fraction)
        images[i][mask] = 0

    for i in pick(cfg.p_coarse_dropout):
        # Coarse dropout: drop cells of a low-resolution grid, upscaled to rectangles.
        side = rng.uniform(*cfg.coarse_size)
        gh, gw = max(1, round(1 / side * h / w * 2)), max(1, round(1 / side))
        cells = (rng.random((gh, gw)) < rng.uniform(*cfg.coarse_fraction)).astype(np.uint8)
        mask = cv2.resize(cells, (w, h), interpolation=cv2.INTER_NEAREST).astype(bool)
        images[i][mask] = 0
    return images
