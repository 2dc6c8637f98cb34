"""Config schemas taken from the code they configure, and a config error as one line.

``kwargs_schema(fn)`` is a dataclass of the keyword arguments ``fn`` takes, its annotations broadened by
hydra-zen to what OmegaConf checks (``int``, ``float | None``, ``tuple[float, float]`` ...; what OmegaConf
cannot check, such as a union of a number and a string, becomes ``Any`` and is left to ``fn``). Stored in
Hydra's ConfigStore (``cicfw.train.schema``), such a schema makes OmegaConf refuse an unknown key or a value
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

from hydra_zen import BuildsFn
from omegaconf import MISSING, DictConfig, OmegaConf
from omegaconf.errors import (ConfigAttributeError, ConfigKeyError, MissingMandatoryValue, OmegaConfBaseException,
                              ValidationError)

from cicfw.core.errors import CicfwError, ConfigError

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


def same_value(a: Any, b: Any) -> bool:
    """Config values equal as numbers (to float noise), or element by element for lists and tuples: a value
    a checkpoint recorded against the one a resumed run gives."""
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(same_value(x, y) for x, y in zip(a, b))
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return math.isclose(float(a), float(b), rel_tol=1e-12, abs_tol=0.0)
    return a == b


def is_integer(v: Any) -> bool:
    """An int, not a bool."""
    return isinstance(v, int) and not isinstance(v, bool)


def checked_probability(key: str, value: Any) -> float:
    """``value`` as a probability: a number in [0, 1], else one ``ValueError`` naming ``key``."""
    if not (is_number(value) and 0.0 <= value <= 1.0):
        raise ConfigError(key, value, "a probability in [0, 1]", f"{key} is a probability in [0, 1], got {value!r}")
    return float(value)


def checked_range(key: str, value: Any, low: float, high: float, low_allowed: bool, words: str) -> tuple[float, float]:
    """``value`` as a range ``[a, b]``: two numbers, a <= b, each within [low, high] (``low`` itself only
    when ``low_allowed``); else one ``ValueError`` naming ``key`` and ``words``, what each end may be."""
    pair = list(value) if isinstance(value, (list, tuple)) else None
    if pair is None or len(pair) != 2 or not all(is_number(v) for v in pair):
        raise ConfigError(key, value, f"a range [low, high] of two numbers, each {words}")
    a, b = float(pair[0]), float(pair[1])
    inside = all((low <= v if low_allowed else low < v) and v <= high for v in (a, b))
    if not inside or a > b:
        raise ConfigError(key, pair, f"a range [low, high] with low <= high, each {words}")
    return a, b


def whole_number(key: str, value: Any, accepted: str = "an integer") -> int:
    """``value`` as an int (an int, or its digits as a string), else one ``ValueError`` naming ``key`` and
    what it accepts: ``seed must be an integer, got 'abc'`` rather than int()'s own message."""
    if is_integer(value):
        return value
    if isinstance(value, str) and re.fullmatch(r"\s*[-+]?\d+\s*", value):
        return int(value)
    raise ConfigError(key, value, accepted)


#: the seeds ``lightning.seed_everything`` (numpy) takes: train's and evaluate's top-level ``seed``
SEED_RANGE = (0, 2**32 - 1)


def checked_seed(value: int, key: str = "seed") -> int:
    """``seed`` (a whole number: the schemas) within ``SEED_RANGE``, else a ``ConfigError`` naming ``key``
    (Lightning's own message for ``seed=-3`` named no key)."""
    if not SEED_RANGE[0] <= value <= SEED_RANGE[1]:
        raise ConfigError(key, value, f"an integer from {SEED_RANGE[0]} to {SEED_RANGE[1]}")
    return value


# ---- schemas from signatures -----------------------------------------------------------------------

#: attributes of a schema dataclass, for messages: what it configures (``mixer 'gtu'``), the arguments cicfw
#: passes itself (key -> what to do instead), what an unknown key is not (``an argument of mixer 'gtu'``)
WHAT, NOT_SETTABLE, IS_NOT = "__cicfw_what__", "__cicfw_not_settable__", "__cicfw_is_not__"


def _builds():
    """hydra-zen's ``BuildsFn``, reading ``int | None`` as ``Optional[int]`` (it would make it ``Any``)."""
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
                  fields: Mapping[str, tuple[Any, Any]] | None = None, not_settable: Mapping[str, str] | None = None,
                  is_not: str | None = None) -> type:
    """A dataclass with a field per keyword argument of ``fn`` (its type and default; an argument without
    a default is ``'???'``, mandatory), ``exclude`` left out, plus ``fields`` (name -> (type, default)).
    For messages: ``what`` names what it configures (``mixer 'gtu'``), ``not_settable`` maps the arguments
    cicfw passes itself (left out too) to what to do instead, ``is_not`` says what an unknown key is not
    (``a Lightning Trainer argument``; default: ``an argument of <what>``)."""
    builds = _builds()
    out: dict[str, tuple[Any, dataclasses.Field]] = {}
    for name, (type_, default) in (fields or {}).items():
        out[name] = (type_, dataclasses.field(default=default))
    left_out = ("self", *exclude, *(not_settable or {}))
    for target in _signatures(fn):
        for f in dataclasses.fields(builds.kwargs_of(target, zen_exclude=left_out)):
            if f.name == "_target_" or f.name in out:
                continue
            if f.default_factory is not dataclasses.MISSING:
                field = dataclasses.field(default_factory=f.default_factory)
            else:
                field = dataclasses.field(default=MISSING if f.default is dataclasses.MISSING else f.default)
            out[f.name] = (f.type, field)
    name = re.sub(r"\W", "_", f"{getattr(fn, '__name__', 'fn')}Config")
    namespace = {WHAT: what, NOT_SETTABLE: dict(not_settable or {}), IS_NOT: is_not or f"an argument of {what}"}
    return dataclasses.make_dataclass(name, [(n, t, f) for n, (t, f) in out.items()], namespace=namespace)


# ---- a refusal as one line -------------------------------------------------------------------------

class SchemaError(CicfwError):
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
    try:
        return typing.get_type_hints(object_type).get(key) if dataclasses.is_dataclass(object_type) else None
    except Exception:  # an annotation that does not resolve: the message goes without "or null"
        return None


def _accepted_words(err: Any, msg: str) -> str | None:
    m = re.search(r"could not be converted to (\w+)", msg)
    if m:
        words = _ACCEPTED.get(m.group(1), m.group(1))
    elif "is not a valid bool" in msg:
        words = "true or false"
    elif re.match(r"Cannot convert '\w+' to string", msg):
        words = "a string"
    elif "is not a ListConfig" in msg:
        words = "a list"
    elif "is not a subclass of" in msg or "is not a DictConfig" in msg:
        words = "a mapping"
    else:
        return None
    type_ = _field_type(getattr(err, "object_type", None), getattr(err, "key", None))
    return f"{words} or null" if type(None) in typing.get_args(type_) else words


def config_error(err: BaseException, prefix: str = "") -> SchemaError | None:
    """OmegaConf's refusal (``err``, or the OmegaConf error a Hydra exception holds) as a ``SchemaError``;
    None when ``err`` is neither. ``prefix`` goes before the key (``row 'mine': ``...)."""
    cause = err if isinstance(err, OmegaConfBaseException) else err.__cause__ or err.__context__
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
        reason = getattr(object_type, NOT_SETTABLE, {}).get(last)
        if reason:
            return SchemaError(f"{prefix}{key} cannot be set: {reason}", key, "not settable")
        what = getattr(object_type, WHAT, None)
        is_not = getattr(object_type, IS_NOT, None) or (f"an argument of {what}" if what else f"a key of '{where}'")
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


def composed_values(node: Any, schema: type, where: str) -> dict[str, Any]:
    """A composed config node as plain data, each value checked once (``check_composed``); a node composing
    did not type with ``schema`` comes merged over its defaults."""
    if not isinstance(node, DictConfig) or OmegaConf.get_type(node) is not schema:
        plain = OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else node
        return OmegaConf.to_container(checked(schema, plain, where), resolve=True)
    check_composed(node, schema, where)
    return OmegaConf.to_container(node, resolve=True)


def check_composed(node: Any, schema: type, where: str = "", skip: tuple[str, ...] = ()) -> None:
    """A composed config node checked once. A node composing typed with ``schema`` had its keys and types
    checked then: only what composing lets through is checked here, a key added with ``+`` past the schema
    of its node, at any depth (``+mixer.foo=1``, ``+runner.foo=1``), and a mandatory value left ``???``.
    Any other node (one composed without the schema, or typed with another: an option whose ``name`` builds
    another registered name) is checked wholly against ``schema`` here (``checked``). ``skip``: the full
    keys of nodes the caller checks itself (``sim``, against the backend its ``name`` builds); the ``hydra``
    node is Hydra's. One ``SchemaError`` naming the full key."""
    if not isinstance(node, DictConfig) or OmegaConf.get_type(node) is not schema:
        checked(schema, plain_values(node) if OmegaConf.is_config(node) else node, where)
        return
    _refuse_added_keys(node, where, ("hydra", *skip))
    missing = _missing_keys(node)
    if missing:
        key = missing[0]
        raise SchemaError(f"{_what(schema, where)} needs {key} (it has no default); add {key}=...", key, "missing")


def _missing_keys(node: Any) -> list[str]:
    """The full keys of the values under ``node`` left ``???``, Hydra's node left out (its interpolations
    resolve only in a running job)."""
    children = [node._get_node(k) for k in node if k != "hydra"]
    return sorted([c._get_full_key(None) for c in children if c._is_missing()]
                  + [k for c in children if OmegaConf.is_config(c) and not c._is_missing()
                     for k in OmegaConf.missing_keys(c)])


def _refuse_added_keys(node: Any, where: str, skip: tuple[str, ...]) -> None:
    """A key added with ``+`` to ``node`` or a node under it typed with a dataclass, refused as composing
    refuses an unknown key (or naming what to do instead of a key cicfw sets)."""
    schema = OmegaConf.get_type(node)
    fields = {f.name for f in dataclasses.fields(schema)}
    for k in map(str, node):
        key = f"{where}.{k}" if where else k
        if key in skip:
            continue
        if k not in fields:
            checked(schema, {k: None}, where)
        child = node._get_node(k)
        if isinstance(child, DictConfig) and dataclasses.is_dataclass(OmegaConf.get_type(child)):
            _refuse_added_keys(child, key, skip)


def plain_value(value: Any) -> Any:
    """A config value as plain data (a ListConfig as a list, resolved), as ``torch.load(weights_only=True)``
    reads it back from a checkpoint."""
    return OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value


def plain_values(cfg: Any) -> dict[str, Any]:
    """A composed app config as plain data (resolved), its ``hydra`` node left out: what ``checked`` takes."""
    return {str(k): plain_value(cfg[k]) for k in cfg if k != "hydra"}


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
    extra = {k: (Any, None) for k in extra_keys}
    checked(kwargs_schema(fn, what, fields=extra, not_settable=set_by_cicfw), kwargs, where)
