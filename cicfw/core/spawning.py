"""Spawned worker processes import the script that started them again: a script must keep its work under
``if __name__ == "__main__":`` or each worker starts the whole run over (and waits on its parent's lock).
``check_spawn_safe`` refuses, in one line, what can be seen cheaply before any worker starts."""
from __future__ import annotations

import ast
import multiprocessing as mp
from multiprocessing import spawn
from pathlib import Path
from typing import Any

from cicfw.core.errors import CicfwError

GUARD = 'if __name__ == "__main__":'


def _is_main_test(test: ast.expr) -> bool:
    """Whether ``test`` is ``__name__ == "__main__"`` (either way round)."""
    if not (isinstance(test, ast.Compare) and len(test.ops) == 1 and isinstance(test.ops[0], ast.Eq)):
        return False
    sides = (test.left, test.comparators[0])
    return (any(isinstance(s, ast.Name) and s.id == "__name__" for s in sides)
            and any(isinstance(s, ast.Constant) and s.value == "__main__" for s in sides))


def script_has_guard(path: str | Path) -> bool | None:
    """Whether the script at ``path`` has an ``if __name__ == "__main__":`` block at its top level; None when
    it cannot be read or parsed (nothing is said then)."""
    try:
        tree = ast.parse(Path(path).read_bytes(), str(path))
    except (OSError, SyntaxError, ValueError):
        return None
    return any(isinstance(node, ast.If) and _is_main_test(node.test) for node in tree.body)


def unguarded_script() -> str | None:
    """The script a spawned worker would run again (the main module started by its path, as
    ``multiprocessing.spawn`` decides) when it has no ``if __name__ == "__main__":`` block; None otherwise
    (``python -m``, an interactive session, a guarded script)."""
    path = spawn.get_preparation_data("cicfw-check").get("init_main_from_path")
    return path if path is not None and script_has_guard(path) is False else None


def check_spawn_safe(what: str, key: str, value: Any) -> None:
    """Before ``what`` starts spawned workers (``key=value`` asked for them): one ``CicfwError`` naming the
    key and the script when this process is itself a worker importing its parent's script (the call is
    outside the guard), or when the script that started it has no guard at all."""
    if getattr(mp.current_process(), "_inheriting", False):
        raise CicfwError(f"{what} was called while a spawned worker process imported the script that started it "
                         f"({key}={value!r} starts workers): call it under {GUARD} in that script",
                         key=key, value=value)
    script = unguarded_script()
    if script is not None:
        raise CicfwError(f"{key}={value!r} starts worker processes, which import {script} again, and it has no "
                         f"{GUARD} block: call {what} under one (or use {key}=1)", key=key, value=value)
