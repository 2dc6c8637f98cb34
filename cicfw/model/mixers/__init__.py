"""Branch mixers, one file each; importing this package registers the built-ins in MIXERS."""
from cicfw.model.mixers.base import Mixer
from cicfw.model.mixers import independent  # noqa: F401  (registers)
from cicfw.model.mixers import cross_stitch, gtu, moe, re, sluice, soft_sharing  # noqa: F401  (register)

__all__ = ["Mixer"]
