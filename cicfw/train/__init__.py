"""Training: ``python -m cicfw.train``. ``app`` composes encoder/mixer/head/data/trainer/speed from the config
and fits (checkpoints, resume, the run's provenance); ``schema`` is the train config's schema.

conf/train.yaml puts its ``schema`` package on Hydra's search path (``pkg://cicfw.train.schema``): importing that registers the
schema in Hydra's ConfigStore before a train config is composed.
"""
