"""Why a model misses turns, measured: ``python -m cicfw.diagnose``. ``app`` is the Hydra app,
``steer_diagnostic`` does the measuring (steering against the expert per junction phase, command swaps);
``schema`` is the diagnose config's schema.

conf/diagnose.yaml puts its ``schema`` package on Hydra's search path (``pkg://cicfw.diagnose.schema``): importing it
registers the schema in Hydra's ConfigStore before a diagnose config is composed.
"""
