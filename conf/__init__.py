# The Hydra config tree, installed as the package ``cicfw.conf`` (see setup.py).
