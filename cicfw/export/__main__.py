"""``python -m cicfw.export``: the export app (``cicfw.export.app``)."""
from cicfw.core.override_hints import run_app
from cicfw.export.app import main

if __name__ == "__main__":
    run_app(main, "export")  # a plugin that fails to import: one warning; a mistyped key: did you mean ...?
