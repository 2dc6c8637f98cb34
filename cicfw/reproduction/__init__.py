"""The reproduction: the paper's Table 4 as rows x seeds x one budget, its lock, its statistics and its report.

``app`` is the app (``python -m cicfw.reproduce`` runs it: plan, cells, report), ``lock`` holds one run
per results folder and ``catalogue`` says what a row is. The rest is numpy/scipy/statsmodels over the cells' episode outcomes, so ``cicfw report``
and the tests use it without training anything: ``cells`` (cell.json as data, the table's columns),
``seed_stats`` (intervals over seeds, the episodes' floor, Holm), ``analysis`` (a folder's estimates, the
episode bootstrap, which cells a comparison pairs), ``claims`` (the paper's claims and their verdicts),
``ranking`` (which row drives best), ``seed_spread`` (do a row's seeds differ beyond the episodes' luck),
``report`` (results.json/.csv, RESULTS.md, the pictures) and ``published`` (docs/results folders: publish,
continue). Two studies over published cells run on their own: ``paired_switch`` (does a switch change
driving) and ``offline_vs_closed_loop`` (does a lower validation error mean a better driver).

``schema`` is the reproduce config's schema: conf/reproduce.yaml puts its ``schema`` package on Hydra's search path
(``pkg://cicfw.reproduction.schema``), and importing that registers the schema in Hydra's ConfigStore before a
reproduce config is composed.
"""
