"""Hydra discovers this SearchPathPlugin in the ``hydra_plugins`` namespace package at startup."""
from hydra.core.config_search_path import ConfigSearchPath
from hydra.plugins.search_path_plugin import SearchPathPlugin


class AttentionMixerSearchPathPlugin(SearchPathPlugin):
    """Appends the plugin's config package, so ``mixer=attention`` works in every cicfw app."""

    def manipulate_search_path(self, search_path: ConfigSearchPath) -> None:
        search_path.append(provider="cicfw-attention-mixer", path="pkg://cicfw_attention_mixer.conf")
