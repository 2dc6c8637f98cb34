"""``python -m cicfw.diagnose``: the diagnose app (``cicfw.diagnose.app``)."""
from cicfw.core.errors import install_app_handlers

if __name__ == "__main__":
    install_app_handlers()  # first, so SIGTERM while the app imports and composes its config is one line
    from cicfw.core.override_hints import run_app
    from cicfw.diagnose.app import main

    run_app(main, "diagnose")  # a plugin that fails to import: one warning; a mistyped key: did you mean ...?
