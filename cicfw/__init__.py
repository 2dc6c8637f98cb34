"""cicfw: conditional imitation (co-)learning for end-to-end steering, on Lightning + Hydra."""

__version__ = "0.2.0"

# Branch order of every mixer output: CIL command code - 2 (codes 2, 3, 4, 5).
COMMANDS = ("follow", "left", "right", "straight")
N_COMMANDS = len(COMMANDS)
# |speed| above this (km/h) is no car's: the data reader refuses a file holding one (cicfw.data.frames), the
# driving agent such an input (cicfw.export.agent), so a model only ever sees speeds it could have trained on.
MAX_ABS_SPEED_KMH = 300.0


def _started_as_app() -> bool:
    """Whether this process is an app started from the command line: ``python -m cicfw[.<app>]`` (while
    ``-m`` imports this package, ``sys.argv[0]`` is ``-m``) or the ``cicfw`` console script."""
    import os
    import sys

    argv = list(getattr(sys, "orig_argv", None) or [])
    if sys.argv[:1] == ["-m"]:
        for i, arg in enumerate(argv[1:], 1):
            if arg == "-m" or (arg.startswith("-m") and not arg.startswith("--")):
                module = arg[2:] or (argv[i + 1] if i + 1 < len(argv) else "")
                return module == "cicfw" or module.startswith("cicfw.")
        return False
    return os.path.basename(sys.argv[0]) == "cicfw" if sys.argv else False


if _started_as_app():  # SIGTERM (and Ctrl-C) during the app's imports: one line, not silence or a traceback
    from cicfw.core.errors import install_app_handlers

    install_app_handlers()
