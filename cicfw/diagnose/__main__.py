"""``python -m cicfw.diagnose``: the diagnose app (``cicfw.diagnose.app``)."""
from cicfw.core.override_hints import run_app
from cicfw.diagnose.app import main

if __name__ == "__main__":
    run_app(main, "diagnose")  # a plugin that fails to import: one warning; a mistyped key: did you mean ...?
