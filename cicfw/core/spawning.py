"""Spawned worker processes import the script that started them again: a script must keep its work under
``if __name__ == "__main__":`` or each worker starts the whole run over (and waits on its parent's lock).
``check_spawn_safe`` refuses, in one line, what can be seen cheaply before any worker starts."""
from __future__ import annotations

import ast
import multiprocessing as mp
import os
import sys
from multiprocessing import spawn
from pathlib import Path
from typing import Any

from cicfw.core.errors import CicfwError

GUARD = 'if __name__ == "__main__":'
# a spawned worker that imported its parent's script and found the call outside the guard exits with this
# status, silently: the parent reads it and says the one line (a traceback per worker told nothing more)
REFUSED_EXIT = 87


def _is_main_test(test: ast.expr) -> bool:
    """Whether ``test`` is ``__name__ == "__main__"`` (either way round)."""
    if not (isinstance(test, ast.Compare) and len(test.ops) == 1 and isinstance(test.ops[0], ast.Eq)):
        return False
    sides = (test.left, test.comparators[0])
    return (any(isinstance(s, ast.Name) and s.id == "__name__" for s in sides)
            and any(isinstance(s, ast.Constant) and s.value == "__main__" for s in sides))


def _guard_lines(path: str | Path) -> list[tuple[int, int]] | None:
    """The line ranges of the top-level ``if __name__ == "__main__":`` blocks of the script at ``path``; None
    when it cannot be read or parsed."""
    try:
        tree = ast.parse(Path(path).read_bytes(), str(path))
    except (OSError, SyntaxError, ValueError):
        return None
    return [(node.lineno, node.end_lineno or node.lineno) for node in tree.body
            if isinstance(node, ast.If) and _is_main_test(node.test)]


def script_has_guard(path: str | Path) -> bool | None:
    """Whether the script at ``path`` has an ``if __name__ == "__main__":`` block at its top level; None when
    it cannot be read or parsed (nothing is said then)."""
    lines = _guard_lines(path)
    return None if lines is None else bool(lines)


def _script_line(script: str) -> int | None:
    """The line of ``script``'s top level (the main module's code) that this call came from, None when it
    does not come from there (a thread, a callback after the script's top level ended)."""
    main = getattr(sys.modules.get("__main__"), "__dict__", None)
    target = os.path.realpath(script)
    found, frame = None, sys._getframe(1)
    while frame is not None:
        code = frame.f_code
        if code.co_name == "<module>" and frame.f_globals is main and os.path.realpath(code.co_filename) == target:
            found = frame.f_lineno
        frame = frame.f_back
    return found


def _rerun_script() -> str | None:
    """The path of the script a spawned worker runs again (the main module started by its path, as
    ``multiprocessing.spawn`` decides); None when workers run none (``python -c``, ``python -m``, a session)."""
    return spawn.get_preparation_data("cicfw-check").get("init_main_from_path")


def check_spawn_safe(what: str, key: str, value: Any) -> None:
    """Before ``what`` starts spawned workers (``key=value`` asked for them): one ``CicfwError`` naming the
    key and the script when the script cannot be imported again (read from standard input, gone), has no
    guard at all, or makes this call outside its guard (each worker would run it again). A worker importing
    its parent's script that reaches this call exits with ``REFUSED_EXIT``, no traceback: its parent says it."""
    if getattr(mp.current_process(), "_inheriting", False):
        raise SystemExit(REFUSED_EXIT)
    script = _rerun_script()
    if script is None:
        return
    if not Path(script).exists():
        raise CicfwError(f"{key}={value!r} starts worker processes, which import the script that started this "
                         f"one again, but it was read from standard input or is gone ({script}): run it from a "
                         f"file (or use {key}=1)", key=key, value=value)
    guards = _guard_lines(script)
    if guards is None:
        return
    if not guards:
        raise CicfwError(f"{key}={value!r} starts worker processes, which import {script} again, and it has no "
                         f"{GUARD} block: call {what} under one (or use {key}=1)", key=key, value=value)
    line = _script_line(script)
    if line is not None and not any(a <= line <= b for a, b in guards):
        raise CicfwError(f"{key}={value!r} starts worker processes, which import {script} again, and {what} is "
                         f"called outside its {GUARD} block (line {line}): each worker would run it again; "
                         f"call it under that block (or use {key}=1)", key=key, value=value)


class WorkerRefused(CicfwError):
    """A spawned worker met the call outside its script's guard: running the same command again cannot help."""


def refused_by_worker(exitcode: int | None, what: str, key: str, value: Any) -> WorkerRefused | None:
    """The one-line error for a worker that exited with ``REFUSED_EXIT`` (it imported the script and met the
    call outside its guard); None for any other exit."""
    if exitcode != REFUSED_EXIT:
        return None
    return WorkerRefused(f"{key}={value!r}: a worker process imported the script that started this one and "
                         f"found {what} called outside its {GUARD} block, where each worker runs it again: call "
                         f"it under that block (or use {key}=1)", key=key, value=value)
