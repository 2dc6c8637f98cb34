"""``python -m cicfw.reproduce``: the paper's Table 4 as rows x seeds x one budget, with intervals and verdicts.

The entry point users, docs and ``cicfw reproduce`` call; the app is ``cicfw.reproduction.app`` (its
docstring says what a run does), beside the reproduction's lock, statistics and report.
"""
from __future__ import annotations

import sys

from cicfw.reproduction.app import main

if __name__ == "__main__":
    from cicfw.registry import guard_hydra_plugins

    guard_hydra_plugins()  # a plugin whose Hydra module fails to import: one warning, not a stopped app
    sys.exit(main())
