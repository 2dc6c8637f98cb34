# Config files shipped with the plugin; hydra_plugins.cicfw_attention_mixer adds this package to
# Hydra's search path, so `mixer=attention` finds mixer/attention.yaml.
