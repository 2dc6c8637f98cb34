"""``python -m cicfw.train``: the train app (``cicfw.train.app``)."""
from cicfw.core.override_hints import run_app
from cicfw.train.app import main

if __name__ == "__main__":
    run_app(main, "train")  # a mistyped key also prints the keys that exist (did you mean ...?)
