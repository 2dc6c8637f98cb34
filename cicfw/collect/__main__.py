"""``python -m cicfw.collect``: the collect app (``cicfw.collect.app``)."""
from cicfw.core.errors import install_app_handlers

if __name__ == "__main__":
    install_app_handlers()  # first, so SIGTERM while the app imports and composes its config is one line
    from cicfw.core.override_hints import run_app
    from cicfw.collect.app import _main

    run_app(_main, "collect")  # a plugin that fails to import: one warning; a mistyped key: did you mean ...?
