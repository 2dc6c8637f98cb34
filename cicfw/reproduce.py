"""``python -m cicfw.reproduce``: the paper's Table 4 as rows x seeds x one budget, with intervals and verdicts.

The entry point users, docs and ``cicfw reproduce`` call; the app is ``cicfw.reproduction.app`` (its
docstring says what a run does), beside the reproduction's lock, statistics and report.
"""
from __future__ import annotations

import sys

from cicfw.core.errors import install_app_handlers

if __name__ == "__main__":
    install_app_handlers()  # first, so SIGTERM while the app imports and composes its config is one line
    from cicfw.core.hydra_plugins import guard_hydra_plugins
    from cicfw.reproduction.app import main

    guard_hydra_plugins()  # a plugin whose Hydra module fails to import: one warning, not a stopped app
    sys.exit(main())
