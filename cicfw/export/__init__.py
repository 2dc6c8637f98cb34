"""Export and inference: ``python -m cicfw.export`` (``app``: a checkpoint as one ONNX or TorchScript graph,
parity-checked, with its sidecar) and ``agent`` (the driving function of a checkpoint or an exported model,
which the suite drives through); ``schema`` is the export config's schema.

conf/export.yaml puts its ``schema`` package on Hydra's search path (``pkg://cicfw.export.schema``): importing that registers
the schema in Hydra's ConfigStore before an export config is composed.
"""
