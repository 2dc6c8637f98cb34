"""``python -m cicfw.collect``: the collect app (``cicfw.collect.app``)."""
from cicfw.collect.app import _main
from cicfw.core.override_hints import run_app

if __name__ == "__main__":
    run_app(_main, "collect")  # a plugin that fails to import: one warning; a mistyped key: did you mean ...?
