"""Closed-loop evaluation: the single-turn suite, the lockstep runner, policies and the report.

``bench`` drives the embedded simulator (``cicfw.sim``) through a plain-Python policy interface
(``cicfw.bench.policy``); only ``cicfw.bench.checkpoint`` touches torch and the model.
"""
