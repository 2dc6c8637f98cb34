"""Output heads, one file each; importing this package registers the built-ins in HEADS."""
from cicfw.model.heads.base import Head
from cicfw.model.heads.bins import SteeringBins
from cicfw.model.heads import regression  # noqa: F401  (registers)
from cicfw.model.heads import coexistence, hybrid, sine, softmax  # noqa: F401  (register)

__all__ = ["Head", "SteeringBins"]
