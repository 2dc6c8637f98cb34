# The Hydra config tree, installed as the package ``cicfw.conf`` (see setup.py).
#
# Importing it (Hydra does, to read pkg://cicfw.conf) registers the collect app's schema
# (``cicfw_collect``: cicfw.collection.config.CollectAppConfig), the first default of conf/collect.yaml.
# The train app's schema needs Lightning and the model, so it is registered by ``cicfw.train_schema``,
# which conf/train.yaml puts on its search path: Hydra imports it when it composes a train config only.
from cicfw.collection.config import register_schema
from cicfw.config_checks import forget_empty_cache_setting

register_schema()
# The configs read the cache folder with ${oc.env:CICFW_CACHE,<default>}, which takes an empty value as
# given; before any of them is resolved, an empty CICFW_CACHE is dropped, so that it means the default.
forget_empty_cache_setting()
