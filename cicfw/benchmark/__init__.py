"""The closed-loop benchmark: the single-turn suite, the lockstep runner, the policies it drives, the
episode journal, and a finished run's report, pictures and videos.

``benchmark`` drives the embedded simulator (``cicfw.sim``) through a plain-Python policy interface
(``cicfw.benchmark.policy``); only ``cicfw.benchmark.checkpoint_policy`` touches torch and the model. Its
modules, one job each: ``suite`` (the episodes), ``runner`` (drives them in lockstep), ``policy`` (the
interface and its registry), ``builtin_policies`` (expert, constant, and ``checkpoint`` registered),
``checkpoint_policy`` (a trained model or an exported one), ``journal`` (``episodes.jsonl``: episodes kept as
they finish), ``finished_run`` (a finished run folder as data: ``Run``, its trajectories, the table's
cells), ``evaluation_report`` (episodes.json/.csv, the success table, joined runs), ``plots`` and ``video``.
The benchmark knows nothing of a reproduction (``cicfw.reproduction`` builds on it).

``app`` is the evaluate app (``python -m cicfw.evaluate`` runs it) and ``schema`` its config's schema:
conf/evaluate.yaml puts its ``schema`` package on Hydra's search path (``pkg://cicfw.benchmark.schema``), and importing it
registers the schema in Hydra's ConfigStore before an evaluate config is composed.
"""
