"""``python -m cicfw.evaluate``: the paper's closed-loop single-turn suite for a checkpoint or a policy.

The entry point users, docs and ``cicfw evaluate`` call; the app is ``cicfw.benchmark.app`` (its docstring
says what a run does), beside the suite, the runner and the policies it drives.
"""
from __future__ import annotations

from cicfw.core.errors import install_app_handlers

if __name__ == "__main__":
    install_app_handlers()  # first, so SIGTERM while the app imports and composes its config is one line
    from cicfw.benchmark.app import main
    from cicfw.core.override_hints import run_app

    run_app(main, "evaluate")  # a plugin that fails to import: one warning; a mistyped key: did you mean ...?
