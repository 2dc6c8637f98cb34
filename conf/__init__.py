# The Hydra config tree, installed as the package ``cicfw.conf`` (see setup.py).
#
# Importing it (Hydra does, to read pkg://cicfw.conf) registers one structured node: an empty mapping
# whose struct flag is off. conf/trainer/*.yaml start from it (`- /cicfw_open_node@_here_`), so the
# trainer node is open: any Lightning Trainer argument can be set without `+`
# (`trainer.fast_dev_run=true`), and cicfw.train checks each key against Trainer.__init__'s
# signature before anything is loaded (a typo gets "did you mean").
from hydra.core.config_store import ConfigStore
from omegaconf import OmegaConf

from cicfw.config_checks import forget_empty_cache_setting

OPEN_NODE = "cicfw_open_node"


def _open_node():
    node = OmegaConf.create({})
    OmegaConf.set_struct(node, False)
    return node


ConfigStore.instance().store(name=OPEN_NODE, node=_open_node(), provider="cicfw")
# The configs read the cache folder with ${oc.env:CICFW_CACHE,<default>}, which takes an empty value as
# given; before any of them is resolved, an empty CICFW_CACHE is dropped, so that it means the default.
forget_empty_cache_setting()
