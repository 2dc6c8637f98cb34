"""Why a model misses turns, measured: ``python -m cicfw.diagnose``. ``app`` is the Hydra app,
``steer_diagnostic`` does the measuring (steering against the expert per junction phase, command swaps);
``schema`` is the diagnose config's schema.

conf/diagnose.yaml puts this package on Hydra's search path (``pkg://cicfw.diagnose``): importing it
registers the schema in Hydra's ConfigStore before a diagnose config is composed.
"""
from cicfw.diagnose import schema  # noqa: F401  (registers the schema)
