"""The ``cicfw`` console script: ``cicfw <command> [args]`` runs ``python -m <module> [args]``."""
from __future__ import annotations

import runpy
import sys
from pathlib import Path

from cicfw.core.errors import install_app_handlers

# command -> (module run as __main__, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "train": ("cicfw.train", "train a model (Hydra app: cicfw train mixer=gtu head=hybrid)"),
    "collect": ("cicfw.collect", "collect CIL HDF5 data with the embedded simulator or CARLA (Hydra app, sim=)"),
    "evaluate": ("cicfw.evaluate", "closed-loop evaluation on the single-turn suite (Hydra app)"),
    "preview": ("cicfw.sim.preview", "write the camera contact sheet and town maps as PNGs"),
    "reproduce": ("cicfw.reproduce", "the paper's Table 4: rows x seeds x a budget, intervals and verdicts"),
    "report": ("cicfw.benchmark.evaluation_report",
               "join evaluation runs into one table (or report a reproduction folder)"),
    "video": ("cicfw.benchmark.video", "film episodes of a finished evaluation run (MP4)"),
    "diagnose": ("cicfw.diagnose", "why a model misses turns: steering vs expert per junction phase, command swaps"),
    "export": ("cicfw.export", "a checkpoint as one ONNX or TorchScript graph, parity-checked (format=onnx|torchscript)"),
    "plugins": ("cicfw.registry", "list registered encoders, mixers, heads and where they come from"),
    "carla-check": ("cicfw.carla_client.check", "test a CARLA server in a minute: PASS/FAIL per guarantee"),
}


#: the report options that take a value (the evaluation report's and the reproduction report's)
REPORT_VALUE_OPTIONS = ("--out", "--publish", "--markdown")


def positionals(args: list[str]) -> list[str]:
    """The arguments that are not options or options' values: the folders ``cicfw report`` is given,
    wherever its options stand (``cicfw report --no-plots DIR`` is DIR's report as ``cicfw report DIR`` is)."""
    found, args = [], iter(args)
    for a in args:
        if a in REPORT_VALUE_OPTIONS:
            next(args, None)
        elif not a.startswith("-"):
            found.append(a)
    return found


def usage() -> str:
    lines = ["usage: cicfw <command> [args...]", "", "commands:"]
    lines += [f"  {name:<11} {help_}" for name, (_, help_) in COMMANDS.items()]
    return "\n".join(lines)


def _is_file(path: Path) -> bool:
    """``path.is_file()``, False where the system refuses to look it up (a name too long for the filesystem:
    the command's own check names it in one line)."""
    try:
        return path.is_file()
    except OSError:
        return False


def main(argv: list[str] | None = None) -> None:
    install_app_handlers()  # first, so SIGTERM while the command imports and composes its config is one line
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help"):
        print(usage())
        return
    if argv[0] not in COMMANDS:
        print(f"cicfw: unknown command {argv[0]!r}; commands: {', '.join(COMMANDS)}", file=sys.stderr)
        sys.exit(2)
    module, _ = COMMANDS[argv[0]]
    folders = positionals(argv[1:])
    if argv[0] == "report" and len(folders) == 1 and _is_file(Path(folders[0]) / "reproduce.json"):
        module = "cicfw.reproduction.report"  # a reproduction's folder: its Table 4 with intervals and verdicts
    # with other folders beside it, the evaluation report refuses it, whichever comes first
    from cicfw.core.hydra_plugins import guard_hydra_plugins

    guard_hydra_plugins()  # a plugin whose Hydra module fails to import: one warning, not a stopped app
    sys.argv = [f"cicfw {argv[0]}", *argv[1:]]
    runpy.run_module(module, run_name="__main__", alter_sys=True)


if __name__ == "__main__":
    main()
