"""Checking a config node against the constructor it is passed to, before anything is built: an
unknown key (with "did you mean" and the accepted keys), a key cicfw sets itself, a missing argument,
and a value of the wrong type (``model.lr=abc``), each as one ``ValueError`` line.

Light on purpose (no torch, no Lightning): the train and evaluate apps both use it up front.
"""
from __future__ import annotations

import difflib
import inspect
import math
import re
from typing import Any, Callable, Mapping

_KEYWORD = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)


def did_you_mean(word: str, options: list[str]) -> str:
    """``"did you mean 'x'? "`` for the closest option, or ``""``."""
    close = difflib.get_close_matches(word, options, n=1, cutoff=0.6)
    return f"did you mean {close[0]!r}? " if close else ""


def _inits(fn: Callable) -> list[Callable]:
    """``fn`` itself, or a class's ``__init__``s along its MRO (``object``'s excluded)."""
    if not inspect.isclass(fn):
        return [fn]
    return [k.__dict__["__init__"] for k in fn.__mro__ if "__init__" in k.__dict__ and k is not object]


def _is_module_init(init: Callable) -> bool:
    """``torch.nn.Module.__init__`` (told apart without importing torch)."""
    return getattr(init, "__module__", "") == "torch.nn.modules.module" and init.__qualname__ == "Module.__init__"


def keyword_parameters(fn: Callable) -> tuple[dict[str, inspect.Parameter], bool]:
    """The keyword parameters ``fn`` takes, and whether it takes any others. A class whose
    ``__init__`` passes ``**kwargs`` on to its base (``HybridHead(W, **bins_kwargs)``) takes its
    bases' arguments too, up to the first ``__init__`` without ``**kwargs``."""
    found: dict[str, inspect.Parameter] = {}
    for init in _inits(fn):
        if inspect.isclass(fn) and _is_module_init(init):
            return found, False  # nn.Module takes no keyword arguments of its own
        params = inspect.signature(init).parameters
        for name, p in params.items():
            if name != "self" and p.kind in _KEYWORD and name not in found:
                found[name] = p
        if not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
            return found, False
    return found, True


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def type_problem(annotation: Any, value: Any) -> str | None:
    """What is wrong with ``value`` for a parameter annotated ``annotation`` (only the plain cases:
    ``int``/``float`` with or without ``None``, and ``tuple[float, ...]`` of a fixed length), else None."""
    ann = annotation if isinstance(annotation, str) else getattr(annotation, "__name__", str(annotation))
    parts = {p.strip() for p in ann.split("|")}
    if value is None and "None" in parts:
        return None
    if parts and parts <= {"int", "float", "None"}:
        return None if _is_number(value) else f"must be a number, got {value!r}"
    fixed = re.fullmatch(r"tuple\[((?:int|float)(?:, *(?:int|float))*)\]", ann.replace(" ", ""))
    if fixed:
        n = len(fixed.group(1).split(","))
        ok = isinstance(value, (list, tuple)) and len(value) == n and all(_is_number(v) for v in value)
        return None if ok else f"must be a list of {n} numbers, got {value!r}"
    return None


def check_kwargs(where: str, what: str, fn: Callable, kwargs: Mapping[str, Any],
                 set_by_cicfw: Mapping[str, str] | None = None, extra_keys: tuple[str, ...] = ()) -> None:
    """One ``ValueError`` for a key ``fn`` does not take (naming the keys it accepts), a key cicfw sets
    itself, a value of the wrong type, or an argument without a default that is missing. ``where`` is
    the config node (``mixer``), ``what`` the thing built (``mixer 'gtu'``)."""
    set_by_cicfw = set_by_cicfw or {}
    named, takes_any = keyword_parameters(fn)
    accepted = sorted([*extra_keys, *(n for n in named if n not in set_by_cicfw)])
    for key, value in kwargs.items():
        if key in set_by_cicfw:
            raise ValueError(f"{where}.{key} cannot be set: {set_by_cicfw[key]}")
        if key not in named and not takes_any:
            raise ValueError(f"{where}.{key} is not an argument of {what}; {did_you_mean(str(key), accepted)}"
                             f"accepted keys: {', '.join(accepted)}")
        problem = type_problem(named[key].annotation, value) if key in named else None
        if problem:
            raise ValueError(f"{where}.{key} {problem}")
    params = inspect.signature(fn).parameters
    missing = [n for n, p in params.items() if n != "self" and p.default is inspect.Parameter.empty
               and p.kind in _KEYWORD and n not in kwargs and n not in set_by_cicfw]
    if missing:
        raise ValueError(f"{what} needs {where}.{missing[0]} (it has no default); add {where}.{missing[0]}=...")
