"""The diagnose app's config schema, registered with Hydra.

conf/diagnose.yaml puts this package on its search path, so Hydra imports it (registering ``cicfw_diagnose``
in its ConfigStore) before it composes a diagnose config, and lays it under the config first: ``data`` takes
``cicfw.diagnose.steer_diagnostic.DataSettings``'s fields (each may be null: the training run's value), ``phases``
``measure``'s phase arguments, and the app's own keys their types here. OmegaConf then refuses an unknown
key or a value of the wrong type while composing, naming its full key, before the run folder exists.
``check`` looks at the composed config only for keys added with ``+`` (which composing lets through);
conf/diagnose.yaml's first callback runs it before Hydra creates the run folder.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import List, Optional

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, DictConfig

from cicfw.core.config_checks import check_composed, kwargs_schema
from cicfw.diagnose.steer_diagnostic import DataSettings, measure

#: camera lists, which DataSettings annotates as any sequence (a type OmegaConf cannot check)
_CAMERAS = (Optional[List[int]], None)
DATA = kwargs_schema(DataSettings, "the frames' settings (DataSettings)", fields={
    **{f.name: (Optional[f.type], None) for f in dataclasses.fields(kwargs_schema(DataSettings, "the frames"))},
    "cameras": _CAMERAS, "val_cameras": _CAMERAS})
PHASES = kwargs_schema(measure, "the junction phases (measure)", fields={"approach_m": (Optional[float], None)},
                       exclude=("frames", "images", "steer_all", "batch_size", "max_frames"))


@dataclass
class DiagnoseConfig:
    """conf/diagnose.yaml: its own keys (their values are written there), the frames and the phases."""

    __cicfw_what__ = "the diagnose config"

    checkpoint: Optional[str] = MISSING
    split: str = MISSING
    data: DATA = field(default_factory=DATA)  # type: ignore[valid-type]
    phases: PHASES = field(default_factory=PHASES)  # type: ignore[valid-type]
    max_frames: Optional[int] = MISSING
    batch_size: int = MISSING
    device: str = MISSING
    threads: Optional[int] = MISSING
    fuse: bool = MISSING
    plot: bool = MISSING


def check(cfg: DictConfig) -> None:
    """What composing let through in a diagnose config (a key added with ``+`` anywhere): one ``SchemaError``
    naming the full key."""
    check_composed(cfg, DiagnoseConfig)


ConfigStore.instance().store(name="cicfw_diagnose", node=DiagnoseConfig, provider="cicfw")
