"""Config schemas taken from the code they configure, and a config error as one line.

``kwargs_schema(fn)`` is a dataclass of the keyword arguments ``fn`` takes, its annotations broadened by
hydra-zen to what OmegaConf checks (``int``, ``float | None``, ``tuple[float, float]`` ...; what OmegaConf
cannot check, such as a union of a number and a string, becomes ``Any`` and is left to ``fn``). Stored in
Hydra's ConfigStore (``cicfw.train_schema``), such a schema makes OmegaConf refuse an unknown key or a value
of the wrong type while the config is composed; ``checked`` applies one to plain values; ``config_error``
turns OmegaConf's refusal (or Hydra's, holding it) into a ``SchemaError``: one line naming the full key, the
value and what is accepted. Also the few checks of values read outside any constructor (``seed=abc``).

Light on purpose (no torch, no Lightning): every app uses it up front.
"""
from __future__ import annotations

import dataclasses
import difflib
import inspect
import math
import os
import re
import types
import typing
from typing import Any, Callable, Mapping

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


def is_number(v: Any) -> bool:
    """A finite int or float, not a bool (YAML's ``true`` is an int to Python)."""
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def is_integer(v: Any) -> bool:
    """An int, not a bool."""
    return isinstance(v, int) and not isinstance(v, bool)


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


# ---- schemas from signatures -----------------------------------------------------------------------

#: the attribute of a schema dataclass that says what it configures (``mixer 'gtu'``), for messages
WHAT = "__cicfw_what__"


def _builds():
    """hydra-zen's ``BuildsFn``, reading ``int | None`` as ``Optional[int]`` (it would make it ``Any``)."""
    from hydra_zen import BuildsFn

    class Builds(BuildsFn):
        @classmethod
        def _sanitized_type(cls, type_: Any, **kwargs: Any) -> Any:
            if isinstance(type_, types.UnionType):
                type_ = typing.Union[type_.__args__]
            return super()._sanitized_type(type_, **kwargs)

    return Builds


def _signatures(fn: Callable) -> list[Callable]:
    """``fn`` itself; for a class, itself and the bases its ``__init__`` hands ``**kwargs`` on to
    (``HybridHead(W, **bins_kwargs)`` takes ``BinnedHead``'s arguments too), up to torch's ``Module``."""
    if not inspect.isclass(fn):
        return [fn]
    found = []
    for k in fn.__mro__:
        init = k.__dict__.get("__init__")
        if init is None or k is object:
            continue
        if getattr(init, "__module__", "") == "torch.nn.modules.module":
            break  # nn.Module takes no keyword arguments of its own
        found.append(k)
        if not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in inspect.signature(init).parameters.values()):
            break
    return found or [fn]


def kwargs_schema(fn: Callable, what: str, exclude: tuple[str, ...] = (),
                  fields: Mapping[str, tuple[Any, Any]] | None = None) -> type:
    """A dataclass with a field per keyword argument of ``fn`` (its type and default; an argument without
    a default is ``'???'``, mandatory), ``exclude`` left out, plus ``fields`` (name -> (type, default)).
    ``what`` names what it configures in messages (``mixer 'gtu'``)."""
    from omegaconf import MISSING

    builds = _builds()
    out: dict[str, tuple[Any, dataclasses.Field]] = {}
    for name, (type_, default) in (fields or {}).items():
        out[name] = (type_, dataclasses.field(default=default))
    for target in _signatures(fn):
        for f in dataclasses.fields(builds.kwargs_of(target, zen_exclude=("self", *exclude))):
            if f.name == "_target_" or f.name in out:
                continue
            if f.default_factory is not dataclasses.MISSING:
                field = dataclasses.field(default_factory=f.default_factory)
            else:
                field = dataclasses.field(default=MISSING if f.default is dataclasses.MISSING else f.default)
            out[f.name] = (f.type, field)
    name = re.sub(r"\W", "_", f"{getattr(fn, '__name__', 'fn')}Config")
    return dataclasses.make_dataclass(name, [(n, t, f) for n, (t, f) in out.items()], namespace={WHAT: what})


# ---- a refusal as one line -------------------------------------------------------------------------

class SchemaError(ValueError):
    """A config value or key the schema refuses, as one line. ``key``: the full key (``mixer.gate_bais``);
    ``kind``: ``unknown key``, ``wrong type``, ``missing`` or ``not settable``."""

    def __init__(self, message: str, key: str, kind: str) -> None:
        super().__init__(message)
        self.key, self.kind = key, kind


#: OmegaConf's names of the types it converts to -> what a message says is accepted
_ACCEPTED = {"Integer": "a whole number", "Float": "a number", "Boolean": "true or false", "String": "a string"}


def _what(object_type: Any, where: str) -> str:
    return getattr(object_type, WHAT, None) or (f"'{where}'" if where else "the config")


def _field_type(object_type: Any, key: Any) -> Any:
    fields = getattr(object_type, "__dataclass_fields__", {})
    return fields[key].type if isinstance(key, str) and key in fields else None


def _accepted_words(err: Any, msg: str) -> str | None:
    m = re.search(r"could not be converted to (\w+)", msg)
    if not m:
        return None
    words = _ACCEPTED.get(m.group(1), m.group(1))
    type_ = _field_type(getattr(err, "object_type", None), getattr(err, "key", None))
    return f"{words} or null" if type(None) in typing.get_args(type_) else words


def config_error(err: BaseException, prefix: str = "") -> SchemaError | None:
    """OmegaConf's refusal (``err``, or the OmegaConf error a Hydra exception holds) as a ``SchemaError``;
    None when ``err`` is neither. ``prefix`` goes before the key (``row 'mine': ``...)."""
    from omegaconf.errors import (ConfigAttributeError, ConfigKeyError, MissingMandatoryValue,
                                  OmegaConfBaseException, ValidationError)

    cause = err if isinstance(err, OmegaConfBaseException) else err.__cause__
    if not isinstance(cause, OmegaConfBaseException):
        return None
    key = str(getattr(cause, "full_key", "") or "")
    msg = str(getattr(cause, "msg", None) or cause).strip().splitlines()[0]
    where, _, last = key.rpartition(".")
    object_type = getattr(cause, "object_type", None)
    if isinstance(cause, (ConfigKeyError, ConfigAttributeError)) and " not in " in msg:
        parent = getattr(cause, "parent_node", None)
        fields = getattr(object_type, "__dataclass_fields__", None)
        keys = sorted(fields) if fields else sorted(str(k) for k in (parent or {}) if str(k) != "hydra")
        hint = did_you_mean(last, keys)
        if not where:
            return SchemaError(f"{prefix}unknown top-level key {last!r}; {hint}accepted top-level keys: "
                               f"{', '.join(keys)}", key, "unknown key")
        what = getattr(object_type, WHAT, None)
        is_not = f"an argument of {what}" if what else f"a key of '{where}'"
        return SchemaError(f"{prefix}{key} is not {is_not}; {hint}accepted keys: {', '.join(keys)}", key, "unknown key")
    if isinstance(cause, MissingMandatoryValue):
        return SchemaError(f"{prefix}{key} has no value (???); give {key}=...", key, "missing")
    value = getattr(cause, "value", None)
    accepted = _accepted_words(cause, msg) if isinstance(cause, ValidationError) else None
    if accepted:
        return SchemaError(f"{prefix}{key} must be {accepted}, got {value!r}", key, "wrong type")
    if isinstance(cause, ValidationError) and "is not Optional" in msg:
        return SchemaError(f"{prefix}{key} cannot be null", key, "wrong type")
    return SchemaError(f"{prefix}{key}: {msg}" if key else f"{prefix}{msg}", key,
                       "wrong type" if isinstance(cause, ValidationError) else "unknown key")


def checked(schema: type, values: Mapping[str, Any], where: str) -> Any:
    """``values`` (plain data) merged over ``schema``'s defaults at ``where`` (``mixer``), as a DictConfig;
    an unknown key, a value of the wrong type or a mandatory value left out is one ``SchemaError`` naming
    the full key."""
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    parts = where.split(".") if where else []
    try:
        typed = OmegaConf.structured(schema)
        root = OmegaConf.create(_nest(parts, typed)) if parts else typed
        merged = OmegaConf.merge(root, _nest(parts, dict(values)))
        missing = sorted(OmegaConf.missing_keys(merged))
    except OmegaConfBaseException as err:
        raise config_error(err) from None
    if missing:
        raise SchemaError(f"{_what(schema, where)} needs {missing[0]} (it has no default); add {missing[0]}=...",
                          missing[0], "missing")
    return OmegaConf.select(merged, where) if parts else merged


def _nest(parts: list[str], values: Any) -> Any:
    for part in reversed(parts):
        values = {part: values}
    return values


def check_kwargs(where: str, what: str, fn: Callable, kwargs: Mapping[str, Any],
                 set_by_cicfw: Mapping[str, str] | None = None, extra_keys: tuple[str, ...] = ()) -> None:
    """``kwargs`` checked against ``fn``'s schema: one ``SchemaError`` for a key ``fn`` does not take, a key
    cicfw sets itself (``set_by_cicfw``: key -> what to do instead), a value of the wrong type or an
    argument without a default left out. ``where`` is the config node (``runner``), ``what`` the thing
    built (``policy 'expert'``); ``extra_keys`` are taken too (``name``)."""
    set_by_cicfw = set_by_cicfw or {}
    for key in kwargs:
        if key in set_by_cicfw:
            raise SchemaError(f"{where}.{key} cannot be set: {set_by_cicfw[key]}", f"{where}.{key}", "not settable")
    extra = {k: (Any, None) for k in extra_keys}
    checked(kwargs_schema(fn, what, tuple(set_by_cicfw), extra), kwargs, where)


# ---- the hand-written checks the schema replaces (removed with cicfw.train_schema) ----
_KEYWORD = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)


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
