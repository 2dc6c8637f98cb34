"""``python -m cicfw.train``: the train app (``cicfw.train.app``)."""
from cicfw.core.errors import install_app_handlers

if __name__ == "__main__":
    install_app_handlers()  # first, so SIGTERM while the app imports and composes its config is one line
    import sys

    from cicfw.core.override_hints import run_app
    from cicfw.train.app import main
    from cicfw.train.schema import without_plus_on_trainer

    sys.argv[1:] = without_plus_on_trainer(sys.argv[1:])  # +trainer.fast_dev_run=true as trainer.fast_dev_run=true
    run_app(main, "train")  # a plugin that fails to import: one warning; a mistyped key: did you mean ...?
