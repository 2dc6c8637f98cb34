"""The ``sim`` config node's schema, one per registered simulator backend: its constructor's arguments and
``name``. The apps that build a backend from their config (evaluate, collect) store these in Hydra's
ConfigStore and check a composed ``sim`` node against the backend its ``name`` builds, so that an unknown
key or a wrong type under ``sim`` is refused naming its full key, before a backend is made.
"""
from __future__ import annotations

import functools
from typing import Any, Mapping

from hydra.core.config_store import ConfigStore

from cicfw.core.config_checks import check_composed, kwargs_schema
from cicfw.registry import SIM_BACKENDS

#: the config group the schemas are stored under: an app's defaults list lays ``cicfw_schema/sim/<name>``
#: under its ``sim`` option (``optional cicfw_schema/sim@sim: ${sim}``)
GROUP = "cicfw_schema/sim"


@functools.lru_cache(maxsize=None)
def backend_schema(name: str) -> type:
    """The schema of the ``sim`` option that builds registered backend ``name``: its arguments and ``name``.
    An unknown name is the registry's ``UnknownNameError``, listing the registered ones."""
    return kwargs_schema(SIM_BACKENDS.get(name), f"sim {name!r}", fields={"name": (str, name)},
                         not_settable={"client": "cicfw connects to the server itself (sim.host, sim.port)"})


def store_backend_schemas() -> None:
    """``cicfw_schema/sim/<name>`` in Hydra's ConfigStore for every registered backend (plugins' too)."""
    store = ConfigStore.instance()
    for name in SIM_BACKENDS.names():
        store.store(group=GROUP, name=name, node=backend_schema(name), provider="cicfw")


def check_sim_node(node: Any, where: str = "sim") -> None:
    """A composed ``sim`` node against the backend its ``name`` builds, once (``check_composed``): a key added
    with ``+``; the whole node where composing typed it as another backend's (a ``name`` other than its
    option file's) or it is plain data. One ``SchemaError`` naming the full key; a name no backend is
    registered under is left to the registry's own error, when the backend is made."""
    if isinstance(node, Mapping) and str(node.get("name")) in SIM_BACKENDS:
        check_composed(node, backend_schema(str(node["name"])), where)
