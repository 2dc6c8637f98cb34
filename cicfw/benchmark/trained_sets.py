"""The towns and weathers a training run's data was collected in, as the ``suite.training_towns`` /
``suite.training_weathers`` of the evaluation after training and of a checkpoint's evaluation: the table's
"training" columns are otherwise the defaults (town_a; ClearNoon, ClearSunset), which label a model trained
in town_b under CloudyNoon as tested in its training town under its training weathers."""
from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any, Sequence

from omegaconf import OmegaConf

from cicfw.benchmark.suite import PAPER_WEATHERS, TRAINING_TOWNS, TRAINING_WEATHERS, town_label
from cicfw.core.run_folder import saved_run_config
from cicfw.core.sweeps import override_values
from cicfw.data.provenance import SETS_KEY, folder_record
from cicfw.model.checkpoint import checkpoint_record, recorded_data_paths
from cicfw.sim.town import town_names

log = logging.getLogger(__name__)


def data_sets(data_cfg: Any) -> tuple[list[str], list[str]] | None:
    """(towns, weathers) the run's data was collected in: those of the ``dataset_metadata.json`` a cicfw
    collection left in ``data.path`` (the towns and weathers its episodes were collected in: a listed one that got
    no episode is not among them), else those of the collection the run makes (``data.collect``: not collected
    yet, or collected with other lists); None when neither says (other data)."""
    if data_cfg is None or not hasattr(data_cfg, "get"):
        return None
    collect = data_cfg.get("collect")
    listed = None
    if collect is not None and collect.get("towns") is not None and collect.get("weathers") is not None:
        listed = [str(t) for t in collect.towns], [str(w) for w in collect.weathers]
    try:
        meta = json.loads((Path(str(data_cfg.get("path"))).expanduser() / "dataset_metadata.json").read_text())
    except (OSError, ValueError, TypeError):
        return listed
    if not (isinstance(meta, dict) and isinstance(meta.get("towns"), list) and isinstance(meta.get("weathers"), list)):
        return listed
    asked = meta.get("config") if isinstance(meta.get("config"), dict) else {}
    asked_lists = [str(t) for t in asked.get("towns") or ()], [str(w) for w in asked.get("weathers") or ()]
    if listed is not None and listed != asked_lists:
        return listed  # the folder holds another collection than the run's node asks for
    return [str(t) for t in meta["towns"]], [str(w) for w in meta["weathers"]]


def recorded_sets(data_cfg: Any) -> dict[str, list[str]] | None:
    """What a run records (``SETS_KEY`` of its data record) when training starts: the towns and weathers its data
    says it was collected in (``data_sets``), so that a later evaluation does not read them from metadata edited
    since; None when the data says none."""
    found = data_sets(data_cfg)
    return None if found is None else {"towns": found[0], "weathers": found[1]}


def _sets(value: Any) -> tuple[list[str], list[str]] | None:
    if isinstance(value, dict) and isinstance(value.get("towns"), list) and isinstance(value.get("weathers"), list):
        return [str(t) for t in value["towns"]], [str(w) for w in value["weathers"]]
    return None


def checkpoint_sets(checkpoint: Path) -> tuple[list[str], list[str]] | None:
    """The (towns, weathers) ``checkpoint``'s run recorded its data was collected in when training started: its
    own data record's, else (a checkpoint without one) its run folder's ``data.json``; an exported model's sidecar
    (``training_dataset``). A run resumed on other data (``resume_on_other_data``) trained on all of them: the
    union over the earlier data its record keeps (``before``) and its current data. None when none records them
    (a checkpoint written before records held them)."""
    found = [s for s in map(_sets, (r.get(SETS_KEY) for r in _trained_records(checkpoint))) if s is not None]
    if not found:
        return None
    return (list(dict.fromkeys(t for towns, _ in found for t in towns)),
            list(dict.fromkeys(w for _, weathers in found for w in weathers)))


def earlier_data(checkpoint: Path) -> int:
    """How many data sets ``checkpoint``'s run trained on before it resumed on its current data (the records
    its data record keeps under ``before``); 0 for a run on one data set, or a checkpoint without a record."""
    return max(len(_trained_records(checkpoint)) - 1, 0)


def _trained_records(checkpoint: Path) -> list[dict[str, Any]]:
    """The data records of every data set ``checkpoint``'s run trained on, earliest first (``before``, then its
    current data's): an exported model's sidecar's (``training_dataset``), else the checkpoint's own record,
    else its run folder's ``data.json``; [] without any."""
    record = _exported_dataset(checkpoint)
    if record is None:
        record = checkpoint_record(checkpoint)
    if record is None:
        record = folder_record(Path(checkpoint).parent.parent)
    if not isinstance(record, dict):
        return []
    before = record.get("before")
    return [*(r for r in (before if isinstance(before, list) else []) if isinstance(r, dict)), record]


def _exported_dataset(model: Path) -> dict[str, Any] | None:
    """The ``training_dataset`` an exported model's sidecar (``<file>.json``) records; None for any other file."""
    try:
        data = json.loads(Path(model).with_name(Path(model).name + ".json").read_text())["training_dataset"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return data if isinstance(data, dict) else None


def training_set_overrides(data_cfg: Any, overrides: Sequence[str],
                           recorded: tuple[list[str], list[str]] | None = None, whose: str | None = None,
                           earlier: int = 0) -> list[str]:
    """``suite.training_towns=[...]`` and ``suite.training_weathers=[...]`` from the run's data, each unless
    ``overrides`` give it; only names the suite accepts as training ones (a shipped town or one the overrides
    drive; one of the paper's weathers or one the overrides drive), so that data collected under other
    weathers leaves none "training" rather than refusing the evaluation. Nothing when the data does not say.
    ``recorded``: the (towns, weathers) a checkpoint recorded when its training started (``checkpoint_sets``):
    they win over the data's metadata now, and a line names both where they differ; ``whose`` (the checkpoint)
    without them: a line says the columns come from the metadata as it is now. ``earlier``: how many data sets
    the run trained on before its current one (``earlier_data``): then ``recorded`` is the union over all, which
    differs from the current data's by design, not by an edit of its metadata."""
    given = override_values(overrides)
    if str(given.get("sim", "embedded")) != "embedded":  # another simulator's towns and weathers: its own names
        return []
    both_given = {"suite.training_towns", "suite.training_weathers"} <= set(given)
    now = data_sets(data_cfg)
    found = now if recorded is None else recorded
    if recorded is not None and now is not None and now != recorded and not both_given and not earlier:
        log.warning("%s recorded when its training started that its data was collected in towns %s, weathers %s; "
                    "the data (%s) says towns %s, weathers %s now: the table's training columns are the recorded "
                    "ones", whose or "the checkpoint", recorded[0], recorded[1], data_cfg.get("path"), now[0], now[1])
    elif recorded is None and whose is not None and now is not None and not both_given:
        log.info("%s records no towns and weathers of its data (written before checkpoints recorded them, or its "
                 "data said none when it trained): the table's training columns are those the data (%s) says now",
                 whose, data_cfg.get("path"))
    if found is None:
        if data_cfg is not None and not both_given:
            # a label nobody chose: say so rather than pass it for the data's
            log.warning("the data (%s) says nothing of the towns and weathers it was collected in (no %s): the "
                        "table's training columns are the suite's defaults (%s; %s) unless suite.training_towns / "
                        "suite.training_weathers name them", data_cfg.get("path") if hasattr(data_cfg, "get") else
                        data_cfg, "dataset_metadata.json", ", ".join(TRAINING_TOWNS), ", ".join(TRAINING_WEATHERS))
        return []
    towns, weathers = found
    known_towns = {*town_names(), *(town_label(t) for t in (given.get("suite.towns") or ()))}  # shipped or driven
    driven_weathers = {str(w) for w in (given.get("suite.weathers") or ())}
    out = []
    if "suite.training_towns" not in given:
        names = [town_label(t) for t in towns]
        kept = [t for t in dict.fromkeys(names) if t in known_towns]
        out.append(f"suite.training_towns=[{','.join(kept)}]")
    if "suite.training_weathers" not in given:
        kept = [w for w in dict.fromkeys(weathers) if w in PAPER_WEATHERS or w in driven_weathers]
        out.append(f"suite.training_weathers=[{','.join(kept)}]")
    return out


def exported_model_data(model: Path) -> Any | None:
    """The ``data`` node of a model ``cicfw export`` wrote: the data folder its sidecar (``<file>.json``)
    records it trained on (``training_dataset.path``); None for any other file or a sidecar that names none."""
    path = (_exported_dataset(model) or {}).get("path")
    return OmegaConf.create({"path": str(path)}) if path else None


def checkpoint_run_data(checkpoint: Path) -> Any | None:
    """The ``data`` node of the run that wrote ``checkpoint`` (``<run>/checkpoints/x.ckpt``): its saved
    ``.hydra/config.yaml``, with ``data.path`` the absolute one the checkpoint (else its run's ``data.json``)
    recorded (the path as typed may be relative to where it trained). Just that path when the folder's config
    is not the checkpoint's (it recorded other data: a checkpoint copied into another run's folder) or there is
    none (``hydra.output_subdir=null``): the data folder's metadata still says where it was collected. None for
    a checkpoint outside such a run. An exported model's is the data its sidecar records."""
    exported = exported_model_data(checkpoint)
    if exported is not None:
        return exported
    own, recorded = recorded_data_paths(checkpoint)
    config = saved_run_config(checkpoint)
    data = config.get("data") if config is not None else None
    if (own and own != recorded) or (config is None and recorded):
        data = OmegaConf.create({})
    if not OmegaConf.is_dict(data):
        return None
    if own or recorded:
        OmegaConf.update(data, "path", str(own or recorded), force_add=True)
    return data
