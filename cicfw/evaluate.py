"""``python -m cicfw.evaluate``: the paper's closed-loop single-turn suite for a checkpoint or a policy.

The entry point users, docs and ``cicfw evaluate`` call; the app is ``cicfw.benchmark.app`` (its docstring
says what a run does), beside the suite, the runner and the policies it drives.
"""
from __future__ import annotations

from cicfw.benchmark.app import main
from cicfw.core.override_hints import run_app

if __name__ == "__main__":
    run_app(main, "evaluate")  # a plugin that fails to import: one warning; a mistyped key: did you mean ...?
