"""cicfw-attention-mixer: the ``attention`` branch mixer for cicfw (registered by entry point)."""
from cicfw_attention_mixer.mixer import AttentionMixer

__all__ = ["AttentionMixer"]
