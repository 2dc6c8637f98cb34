"""Checking a config node against the constructor it is passed to, before anything is built: an
unknown key (with "did you mean" and the accepted keys), a key cicfw sets itself, a missing argument,
and a value of the wrong type (``model.lr=abc``, ``trainer.max_epochs=abc`` against Lightning's typing
annotations), each as one ``ValueError`` line; ``whole_number`` for the integers read outside any
constructor (``seed=abc``).

Light on purpose (no torch, no Lightning): the train and evaluate apps both use it up front.
"""
from __future__ import annotations

import difflib
import inspect
import math
import os
import re
import types
import typing
from typing import Any, Callable, Mapping

_KEYWORD = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)


#: the environment variable naming cicfw's cache folder (datasets, compiled code); the configs read it
#: with ``${oc.env:CICFW_CACHE,<default>}``
CACHE_VARIABLE = "CICFW_CACHE"


def forget_empty_cache_setting() -> None:
    """Drop ``CICFW_CACHE`` from the environment when it is set but empty, so that it means unset (the
    default ``~/.cache/cicfw``), as ``cicfw.model.speed.cache_dir`` reads it. ``oc.env`` takes an empty
    value as given: ``/datasets/...`` at the file-system root."""
    if os.environ.get(CACHE_VARIABLE) == "":
        del os.environ[CACHE_VARIABLE]


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


def is_number(v: Any) -> bool:
    """A finite int or float, not a bool (YAML's ``true`` is an int to Python)."""
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def is_integer(v: Any) -> bool:
    """An int, not a bool."""
    return isinstance(v, int) and not isinstance(v, bool)


#: the annotation parts a config value can be checked against (classes, ``list[int]`` ... are not)
_PLAIN = ("int", "float", "bool", "str", "None")


def _parts(annotation: Any) -> tuple[list[str], list[Any]] | None:
    """An annotation's type names and ``Literal`` values, from its text (``int | None``, as
    ``from __future__ import annotations`` keeps it) or its typing object (``Optional[int]``, as
    ``lightning.Trainer`` has it); None when a part is none of ``_PLAIN`` (nothing to check)."""
    if isinstance(annotation, str):
        names = [p.strip() for p in annotation.split("|")]
        return (names, []) if all(n in _PLAIN for n in names) else None
    if annotation is type(None) or annotation is None:
        return ["None"], []
    origin = typing.get_origin(annotation)
    if origin is typing.Literal:
        return [], list(typing.get_args(annotation))
    if origin in (typing.Union, types.UnionType):
        found = [_parts(a) for a in typing.get_args(annotation)]
        if any(f is None for f in found):
            return None
        return [n for f in found for n in f[0]], [v for f in found for v in f[1]]
    name = getattr(annotation, "__name__", None)
    return ([name], []) if origin is None and name in _PLAIN else None


def _fits(names: list[str], literals: list[Any], value: Any) -> bool:
    """Whether ``value`` is one of ``names``' types or ``literals`` (a number is a valid ``str``: Hydra
    reads ``name=123`` as one)."""
    if any(value == v and type(value) is type(v) for v in literals):
        return True
    if isinstance(value, bool):
        return "bool" in names
    return (("None" in names and value is None) or ("str" in names and isinstance(value, (str, int, float)))
            or ("float" in names and is_number(value)) or ("int" in names and isinstance(value, int)))


def _accepted(names: list[str], literals: list[Any], value: Any) -> str:
    """``a number or null``, ``true or false``, ``true, false, 'warn' or null`` ...; an ``int`` is "a
    number" to a value that is none, and "a whole number" to a fraction."""
    whole = "a whole number" if is_number(value) else "a number"
    words = {"int": [whole] if "float" not in names else [], "float": ["a number"], "bool": ["true", "false"],
             "str": ["a string"]}
    said = [w for n in dict.fromkeys(names) for w in words.get(n, [])]
    said += [repr(v) for v in literals] + (["null"] if "None" in names else [])
    return said[0] if len(said) == 1 else f"{', '.join(said[:-1])} or {said[-1]}"


def type_problem(annotation: Any, value: Any) -> str | None:
    """What is wrong with ``value`` for a parameter annotated ``annotation``, else None. Checked: unions of
    ``int``, ``float``, ``bool``, ``str``, ``None`` and ``Literal`` values (as text or typing objects),
    and ``tuple[float, ...]`` of a fixed length; any other annotation passes (its callee checks it)."""
    ann = annotation if isinstance(annotation, str) else getattr(annotation, "__name__", str(annotation))
    fixed = re.fullmatch(r"tuple\[((?:int|float)(?:, *(?:int|float))*)\]", ann.replace(" ", ""))
    if fixed:
        n = len(fixed.group(1).split(","))
        ok = isinstance(value, (list, tuple)) and len(value) == n and all(is_number(v) for v in value)
        return None if ok else f"must be a list of {n} numbers, got {value!r}"
    parts = _parts(annotation)
    if parts is None or set(parts[0]) <= {"None"} or _fits(*parts, value):
        return None  # Literal values only (trainer.precision): the callee names the accepted ones
    return f"must be {_accepted(*parts, value)}, got {value!r}"


def checked_probability(key: str, value: Any) -> float:
    """``value`` as a probability: a number in [0, 1], else one ``ValueError`` naming ``key``."""
    if not (is_number(value) and 0.0 <= value <= 1.0):
        raise ValueError(f"{key} is a probability in [0, 1], got {value!r}")
    return float(value)


def checked_range(key: str, value: Any, low: float, high: float, low_allowed: bool, words: str) -> tuple[float, float]:
    """``value`` as a range ``[a, b]``: two numbers, a <= b, each within [low, high] (``low`` itself only
    when ``low_allowed``); else one ``ValueError`` naming ``key`` and ``words``, what each end may be."""
    pair = list(value) if isinstance(value, (list, tuple)) else None
    if pair is None or len(pair) != 2 or not all(is_number(v) for v in pair):
        raise ValueError(f"{key} must be a range [low, high] of two numbers, each {words}, got {value!r}")
    a, b = float(pair[0]), float(pair[1])
    inside = all((low <= v if low_allowed else low < v) and v <= high for v in (a, b))
    if not inside or a > b:
        raise ValueError(f"{key} must be a range [low, high] with low <= high, each {words}, got {pair!r}")
    return a, b


def whole_number(key: str, value: Any, accepted: str = "an integer") -> int:
    """``value`` as an int (an int, or its digits as a string), else one ``ValueError`` naming ``key`` and
    what it accepts: ``seed must be an integer, got 'abc'`` rather than int()'s own message."""
    if is_integer(value):
        return value
    if isinstance(value, str) and re.fullmatch(r"\s*[-+]?\d+\s*", value):
        return int(value)
    raise ValueError(f"{key} must be {accepted}, got {value!r}")


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
