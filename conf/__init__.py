# The Hydra config tree, installed as the package ``cicfw.conf`` (see setup.py).
#
# The apps' config schemas are registered by the packages each app config puts on its search path
# (cicfw.train.schema, cicfw.benchmark.schema, cicfw.collect.schema, ...): Hydra imports one when it
# composes that app's config only. Importing it changes nothing else: the apps' entry points
# (``install_app_handlers``) make an empty CICFW_CACHE mean the default cache before composing.
