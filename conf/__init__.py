# The Hydra config tree, installed as the package ``cicfw.conf`` (see setup.py).
#
# The apps' config schemas are registered by the packages each app config puts on its search path
# (cicfw.train.schema, cicfw.benchmark.schema, cicfw.collect.schema, ...): Hydra imports one when it
# composes that app's config only.
from cicfw.core.config_checks import forget_empty_cache_setting

# The configs read the cache folder with ${oc.env:CICFW_CACHE,<default>}, which takes an empty value as
# given; before any of them is resolved, an empty CICFW_CACHE is dropped, so that it means the default.
forget_empty_cache_setting()
