"""A reproduction's cells as data: one ``cell.json`` per (row, seed), every episode's outcome, and the
table's columns and selectors (a column, a town, a weather, overall) that results are read on."""
from __future__ import annotations

import json
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.errors import HydraException

from cicfw.benchmark.finished_run import cell_key, cell_name
from cicfw.benchmark.suite import CELLS
from cicfw.core.errors import CicfwError
from cicfw.core.json_files import read_json
from cicfw.reproduction.catalogue import override_key, speed_node_spelling

#: cell.json's key naming the embedded simulator's weather family its suite was driven under (absent in cells
#: written before it was recorded, and for another simulator: such a cell reads as its folder's)
FAMILY_KEY = "weather_family"
COLUMNS = tuple(cell_key(*c) for c in CELLS)  # training_town/training_weathers ... new_town/new_weathers
COLUMN_NAMES = tuple(cell_name(*c) for c in CELLS)
#: what a part of a claim compares: one table column, or the mean of several (overall: all four)
SELECTORS: dict[str, tuple[int, ...]] = {
    **{c: (i,) for i, c in enumerate(COLUMNS)},
    "overall": (0, 1, 2, 3),
    "training_town": (0, 1), "new_town": (2, 3), "training_weathers": (0, 2), "new_weathers": (1, 3),
}
SELECTOR_NAMES = {**dict(zip(COLUMNS, COLUMN_NAMES)), "overall": "overall", "training_town": "training town",
                  "new_town": "new town", "training_weathers": "training weathers", "new_weathers": "new weathers"}


@dataclass
class CellResult:
    """One finished (row, seed) cell: every episode's success, keyed by episode key."""

    row: str
    seed: int
    episodes: dict[str, dict[str, Any]]  # key -> {"success": bool, "column": str, "command": str}
    meta: dict[str, Any] = field(default_factory=dict)  # the whole cell.json (machine, code, wall_s, curve, ...)

    def rate(self, column: str | None = None) -> float:
        """Success (%) on one table column, or the mean of the four columns (``None``)."""
        if column is None:
            return float(np.mean([self.rate(c) for c in COLUMNS]))
        v = [e["success"] for e in self.episodes.values() if e["column"] == column]
        return 100.0 * float(np.mean(v)) if v else float("nan")

    def value(self, on: str) -> float:
        """Success (%) on a selector of ``SELECTORS``: the mean of its columns' rates."""
        return float(np.mean([self.rate(COLUMNS[i]) for i in SELECTORS[on]]))

    @property
    def cpu(self) -> str:
        """The kind of machine the cell ran on (``machine_kind`` of its ``machine``): its CPU kind, plus its GPU
        where it had one; named ``cpu`` as results.json's keys are."""
        return machine_kind(self.meta.get("machine"))

    def counts(self, column: str, command: str | None = None) -> tuple[int, int]:
        """(successes, episodes) in one table column, or in its episodes of one command."""
        v = [bool(e["success"]) for e in self.episodes.values()
             if e["column"] == column and (command is None or e.get("command") == command)]
        return sum(v), len(v)


def recorded_family(cell: CellResult, folder_family: str | None) -> str | None:
    """The weather family a cell drove under: the one its cell.json records (an empty one too, which names no
    family and so matches none), else, with no record, its folder's."""
    value = cell.meta.get(FAMILY_KEY)
    return folder_family if value is None else value


def check_families(cells: Sequence[CellResult], folder_family: str | None, where: str) -> str | None:
    """The one weather family ``cells`` drove under (``recorded_family``), else one error line naming the cell
    and both families: the same weather names mean other weathers in another family, so their episode keys
    match but their rates do not compare. ``folder_family`` None: not known, the first recorded one counts."""
    known = folder_family
    for c in cells:
        family = recorded_family(c, known)
        if known is not None and family != known:
            raise CicfwError(f"cell {c.row}/seed{c.seed} in {where} was driven under the weather family "
                             f"{family!r}, the folder under {known!r}: their weathers differ under the same names; "
                             f"keep cells of one family in one folder", key=FAMILY_KEY, value=family)
        known = family
    return known


def check_same_episodes(cell: CellResult, reference: CellResult, why: str,
                        names: tuple[str, str] | None = None) -> None:
    """One error line when ``cell`` drove other episodes than ``reference`` (naming both, ``names`` or their
    row/seed, and their counts): rates on other episodes do not compare."""
    if set(cell.episodes) != set(reference.episodes):
        a, b = names or (f"{cell.row}/seed{cell.seed}", f"{reference.row}/seed{reference.seed}")
        apart = len(set(cell.episodes) ^ set(reference.episodes))
        raise CicfwError(f"cell {a} drove other episodes than {b} ({len(cell.episodes)} episodes against "
                         f"{len(reference.episodes)}, {apart} not in both): {why}", key="episodes", value=a)


#: joins a machine kind's CPU kind and its GPU: "Intel Xeon + NVIDIA H100"
GPU_JOIN = " + "
#: a comparison's mark where it pools kinds: of CPUs alone, or where a GPU is among them
MIXED_CPUS, MIXED_MACHINES = "mixed CPUs", "mixed machines"


def _first_parentheses(text: str) -> tuple[int, int] | None:
    """The span of ``text``'s first parentheses, nested ones included: (index of "(", index of its ")")."""
    start = text.find("(")
    if start < 0:
        return None
    depth, end = 0, len(text)
    for i in range(start, len(text)):
        depth += {"(": 1, ")": -1}.get(text[i], 0)
        if depth == 0:
            end = i
            break
    return start, end


def cpu_kind(machine: str | None) -> str:
    """The kind of CPU a cell's ``machine`` names, "2 cores (AMD EPYC), no GPU, ..." -> "AMD EPYC": the text
    in its first parentheses without trademark marks or a trailing "Processor" / "CPU @ 2.9GHz"."""
    if not machine:
        return "unknown CPU"
    text = str(machine)
    span = _first_parentheses(text)
    if span is None:
        return text.split(",")[0].strip() or "unknown CPU"
    name = re.sub(r"\((?:R|TM)\)", "", text[span[0] + 1:span[1]], flags=re.I)
    name = re.sub(r"\s+(?:Processor|CPU)\b.*$", "", name)
    return " ".join(name.split()) or "unknown CPU"


def gpu_kind(machine: str | None) -> str | None:
    """The GPU a cell's ``machine`` names after its CPU, "..., NVIDIA H100 80GB HBM3, Python ..." ->
    "NVIDIA H100" (without trademark marks or a trailing memory size); None for "no GPU" or none named."""
    text = str(machine or "")
    span = _first_parentheses(text)
    if span is None:
        return None
    field = text[span[1] + 1:].lstrip(" ,").split(",")[0].strip()
    if not field or field.lower() == "no gpu" or re.match(r"(?:Python|torch)\b", field):
        return None
    name = re.sub(r"\((?:R|TM)\)", "", field, flags=re.I)
    name = re.sub(r"[\s-]*\d+\s*GB\b.*$", "", name, flags=re.I)
    return " ".join(name.split()) or None


def machine_kind(machine: str | None) -> str:
    """What rows are compared within: the CPU kind, plus the GPU where the cell had one ("Intel Xeon +
    NVIDIA H100"; "Intel Xeon" alone for no GPU). The same seed trains another model on another CPU, and
    on a GPU (its kernels sum in another order) even more surely."""
    gpu = gpu_kind(machine)
    return cpu_kind(machine) + (f"{GPU_JOIN}{gpu}" if gpu else "")


def kind_noun(kinds: Iterable[str]) -> str:
    """How the report names ``kinds``: "CPU" where each is a CPU alone (they differ only by CPU), "machine"
    where one had a GPU."""
    return "machine" if any(GPU_JOIN in k for k in kinds) else "CPU"


def most_first(values: Iterable[str]) -> dict[str, int]:
    """Each value -> how often it occurs, most first (ties by name)."""
    return dict(sorted(Counter(values).items(), key=lambda kv: (-kv[1], kv[0])))


def cpu_counts(cells: Sequence[CellResult]) -> dict[str, int]:
    """Machine kind (``CellResult.cpu``) -> number of ``cells`` that ran on it, most cells first (ties by name)."""
    return most_first(c.cpu for c in cells)


def check_episodes(path: Path, episodes: Any) -> dict[str, dict[str, Any]]:
    """A finished cell's ``episodes``, each checked: an object whose ``success`` is a JSON boolean and whose
    ``column`` is a table column, else one ``CicfwError`` naming the file, the episode and the value (a
    hand-edited 2 or "false" would otherwise surface as matplotlib's or numpy's message, far from its cause)."""
    if not isinstance(episodes, dict):
        raise CicfwError(f"{path}: 'episodes' is {json.dumps(episodes)[:40]}; a finished cell's episodes must be a "
                         f"JSON object of episode key -> outcome", key="episodes", value=episodes)
    for k, e in episodes.items():
        if not isinstance(e, dict):
            raise CicfwError(f"{path}: episode {k!r} is {json.dumps(e)[:40]}; each episode must be a JSON object "
                             f"with 'success' and 'column'", key=f"episodes.{k}", value=e)
        if not isinstance(e.get("success"), bool):
            raise CicfwError(f"{path}: episode {k!r} has success {json.dumps(e.get('success'))[:40]}; it must be "
                             f"a JSON boolean, true or false", key=f"episodes.{k}.success", value=e.get("success"))
        if e.get("column") not in COLUMNS:
            raise CicfwError(f"{path}: episode {k!r} has column {json.dumps(e.get('column'))[:60]}; it must be one "
                             f"of the table's columns, {', '.join(COLUMNS)}", key=f"episodes.{k}.column",
                             value=e.get("column"))
        if not isinstance(e.get("command"), str):
            raise CicfwError(f"{path}: episode {k!r} has command {json.dumps(e.get('command'))[:40]}; it must be the "
                             f"manoeuvre's name as a string (left, right, ...)", key=f"episodes.{k}.command",
                             value=e.get("command"))
    return episodes


def check_curve(path: Path, curve: Any) -> None:
    """A finished cell's ``curve`` (absent or null for none): a list of points, each a JSON object whose
    ``samples`` is a whole number >= 0 and whose ``overall`` is null (a suite that lacks a column) or a
    success rate, a number from 0 to 100; else one ``CicfwError`` naming the file and the key (the report's
    learning curve would otherwise fail with numpy's or matplotlib's message, or draw the edit as data)."""
    if curve is None:
        return
    if not isinstance(curve, list):
        raise CicfwError(f"{path}: 'curve' is {json.dumps(curve)[:40]}; a finished cell's curve must be a JSON list "
                         f"of points ({{\"samples\": ..., \"overall\": ...}}), or [] for none",
                         key="curve", value=curve)
    for i, p in enumerate(curve):
        if not isinstance(p, dict):
            raise CicfwError(f"{path}: 'curve[{i}]' is {json.dumps(p)[:40]}; each point must be a JSON object "
                             f"with 'samples' and 'overall'", key=f"curve.{i}", value=p)
        samples, overall = p.get("samples"), p.get("overall")
        if isinstance(samples, bool) or not isinstance(samples, int) or samples < 0:
            raise CicfwError(f"{path}: 'curve[{i}].samples' is {json.dumps(samples)[:40]}; it must be the "
                             f"number of training samples seen, a whole number >= 0", key=f"curve.{i}.samples",
                             value=samples)
        if overall is not None and (isinstance(overall, bool) or not isinstance(overall, (int, float))
                                    or not 0 <= overall <= 100):  # NaN fails the range too
            raise CicfwError(f"{path}: 'curve[{i}].overall' is {json.dumps(overall)[:40]}; it must be a success "
                             f"rate in percent, a number from 0 to 100 (or null where the suite lacks a column)",
                             key=f"curve.{i}.overall", value=overall)


def load_cell(path: Path) -> CellResult | dict[str, Any]:
    """One ``cell.json``: its CellResult when it finished (status ok, its episodes and its learning curve
    checked: ``check_episodes``, ``check_curve``), else the file's dict as it is."""
    d = read_json(path, kind=dict)
    if d.get("status") == "ok":
        row, seed = d.get("row"), d.get("seed")
        if not isinstance(row, str) or not row:
            raise CicfwError(f"{path}: 'row' is {json.dumps(row)[:40]}; a finished cell names its row as a string",
                             key="row", value=row)
        if isinstance(seed, bool) or not isinstance(seed, int):
            raise CicfwError(f"{path}: 'seed' is {json.dumps(seed)[:40]}; a finished cell's seed is a whole number",
                             key="seed", value=seed)
        check_curve(path, d.get("curve"))
        return CellResult(row=row, seed=seed, episodes=check_episodes(path, d.get("episodes")), meta=d)
    return d


def cell_files(folder: Path) -> list[Path]:
    """Every ``cells/<row>/seed<k>/cell.json`` under a results folder, in a fixed order."""
    return sorted(Path(folder).glob("cells/*/seed*/cell.json"))


#: what a cell's folder holds beside its cell.json in a results folder (its training and its driving); a
#: published folder copies the cell.json alone
CELL_RUNS = ("train", "evaluate")


def cell_runs(folder: Path) -> list[str]:
    """The runs a folder's cells hold (``cells/<row>/seed<k>/train`` ..., relative paths, sorted): some for a
    results folder, none for a published one."""
    folder = Path(folder)
    return sorted(str(d.relative_to(folder)) for name in CELL_RUNS for d in folder.glob(f"cells/*/seed*/{name}"))


#: the key of a cell.json that names a cell among its row's rather than records what it measured: a copy of
#: another seed of the row differs in it alone (the fallback signature, for a cell that lacks ``SIGNATURE``'s)
NAMING_KEYS = ("seed",)
#: what one training run records and no other can repeat: its validation error to every digit and its
#: learning curve, with the episodes its model drove (one model driven again under another suite is no copy)
SIGNATURE = ("val_steer_mae", "curve", "episodes")
#: how an error line says what made two cells one (``measured``)
COPY_SAID = ("the same val_steer_mae, curve and episodes, or, where it records none, cell.json identical but "
             "for its seed")


def measured(cell: CellResult) -> str:
    """A cell's copy signature, one canonical string: its ``SIGNATURE`` fields where it records a validation
    error (a float) and a curve, which two trained models never share and a retouched copy (its wall time
    edited) still does; else its whole cell.json but for its seed."""
    meta = cell.meta
    mae = meta.get("val_steer_mae")
    if isinstance(mae, float) and "curve" in meta:
        return json.dumps({k: meta.get(k) for k in SIGNATURE}, sort_keys=True)
    return json.dumps({k: v for k, v in meta.items() if k not in NAMING_KEYS}, sort_keys=True)


def is_copy(a: CellResult, b: CellResult) -> bool:
    """Whether ``a`` and ``b`` are one cell twice: the same copy signature (``measured``), whatever their rows:
    the paired switch refuses such a paired seed, ``load_cells`` any two such cells of a folder."""
    return measured(a) == measured(b)


def check_no_copies(cells: Sequence[tuple[Path, CellResult]]) -> None:
    """One error line naming two cells that are copies (``is_copy``), of one row or of two: one model counted
    as two seeds would narrow the row's interval as an independent seed does, and one counted in two rows (its
    row, recipe and overrides edited) would make their difference nothing but the episodes' luck."""
    seen: dict[str, tuple[Path, CellResult]] = {}
    for path, cell in cells:
        first, other = seen.setdefault(measured(cell), (path, cell))
        if first != path:
            what = ("two seeds" if other.row == cell.row
                    else f"a seed of both row {other.row!r} and row {cell.row!r}")
            raise CicfwError(f"{first} and {path} are copies of one cell ({COPY_SAID}): one model counted as {what}; "
                             f"remove the copy", key="cell", value=str(path))


#: the names that say which model a cell trained (its recipe's, else the cell.json's own ``mixer``/``head``)
MODEL_NAMES = ("encoder", "mixer", "head")


def model_names(meta: Mapping[str, Any]) -> dict[str, Any]:
    """A cell's recorded model as recipe keys, ``mixer.name`` -> ``gtu``: its recipe's encoder, mixer and head
    names, else (a cell without a recipe) its cell.json's ``mixer`` and ``head``; what it does not record is
    left out (not compared)."""
    recipe = meta.get("recipe") if isinstance(meta.get("recipe"), dict) else {}
    out = {}
    for part in MODEL_NAMES:
        section = recipe.get(part)
        name = section.get("name") if isinstance(section, dict) else meta.get(part)
        if name is not None:
            out[f"{part}.name"] = name
    return out


def check_one_model(cells: Sequence[tuple[Path, CellResult]]) -> None:
    """One error line (``check_cell_pin``'s: the cell's file, the key, both values) when a row's cells record
    different models (``model_names``): a cell of another row copied in with its ``row`` edited would be
    averaged in as a seed of this one."""
    _check_row_values(cells, model_names)


def check_one_recipe(cells: Sequence[tuple[Path, CellResult]]) -> None:
    """As ``check_one_model``, for every recipe key a row's cells both record (``recipe``): a row whose experiment
    file was edited between the runs that trained its cells would pool two models as seeds of one."""
    _check_row_values(cells, lambda meta: flat(meta["recipe"]) if isinstance(meta.get("recipe"), dict) else {})


def _check_row_values(cells: Sequence[tuple[Path, CellResult]], values: Callable[[Mapping[str, Any]], dict]) -> None:
    """Each row's cells agree on the keys ``values(cell.json)`` gives that both record (the row's first cell
    recording a key is the reference), else ``check_cell_pin``'s line naming the cell, the key and both values."""
    known: dict[str, dict[str, tuple[Any, Path]]] = {}
    for path, cell in cells:
        names, row = values(cell.meta), known.setdefault(cell.row, {})
        pin = CellPin(recipe={k: v for k, (v, _) in row.items()})
        found = cell_mismatch({"recipe": names}, pin)
        if found is not None:
            first = row[found[0].removeprefix("recipe.")][1]
            check_cell_pin(path, {"recipe": names}, pin, f"the cell {str(first)!r} of row {cell.row!r} was made with",
                           "a row's cells are one model trained on several seeds; move the cell to its own row or "
                           "remove it")
        for k, v in names.items():
            row.setdefault(k, (v, path))


def load_cells(results_dir: Path) -> tuple[list[CellResult], list[dict[str, Any]]]:
    """The finished cells (status ok) and the failed ones (their cell.json) under ``results_dir``; a cell in
    another's folder, a row's cells that record different models (``check_one_model``) or two cells that are
    copies (``check_no_copies``) are one error line."""
    ok, failed, where = [], [], []
    for p in cell_files(results_dir):
        c = load_cell(p)
        if isinstance(c, CellResult) and (c.row, f"seed{c.seed}") != (p.parent.parent.name, p.parent.name):
            # a cell folder copied under another name (seed0 as seed2) would count its seed twice
            raise CicfwError(f"{p}: a cell of row {c.row!r} seed {c.seed} in the folder of row "
                             f"{p.parent.parent.name!r} {p.parent.name}: each cell lies in cells/<row>/seed<k>; "
                             f"move it back or remove the copy", key="cell", value=str(p))
        (ok if isinstance(c, CellResult) else failed).append(c)
        if isinstance(c, CellResult):
            where.append((p, c))
    check_one_model(where)
    check_no_copies(where)
    return ok, failed


def pooled_counts(cells: Sequence[CellResult], column: str) -> tuple[int, int]:
    """(successes, episodes) in one table column, pooled over ``cells``: the episodes' floor's input."""
    k, n = (sum(x) for x in zip(*(c.counts(column) for c in cells)))
    return k, n


def episode_terms(cells: Mapping[str, Sequence[CellResult]],
                  contrast: Iterable[tuple[float, str, str]]) -> list[tuple[float, int, int]] | None:
    """A contrast of selectors on the episodes pooled over each row's cells, ``(coefficient, row, selector)``
    each (``cells``: row -> its cells), as ``seed_stats.contrast_interval`` takes it: ``(c / k, successes,
    episodes)`` for each of a selector's k columns (a selector is their mean), the coefficients of a
    (row, column) met twice summed, as one proportion is not two independent ones. None where a column has
    no episode (its rate, and so the contrast, is undefined)."""
    weights: dict[tuple[str, str], float] = {}
    for c, row, on in contrast:
        for i in SELECTORS[on]:
            key = (row, COLUMNS[i])
            weights[key] = weights.get(key, 0.0) + c / len(SELECTORS[on])
    terms = [(w, *pooled_counts(cells[row], col)) for (row, col), w in weights.items() if w != 0.0]
    return terms if all(n > 0 for _, _, n in terms) else None


#: the parts of a cell's training config that decide what it learns, kept in its cell.json (``recipe``):
#: the network, the losses, the optimizer, the data pipeline (not where the data lies or how it is read)
RECIPE = ("encoder", "mixer", "head", "model", "data")
RECIPE_DATA_SKIP = ("path", "collect", "num_workers", "in_memory", "val_batch_size", "seed")


def flat(d: Any, prefix: str = "") -> dict[str, Any]:
    """A nested dict as ``a.b.c`` -> value (a recipe compared key by key)."""
    if isinstance(d, dict):
        out = {}
        for k, v in d.items():
            out.update(flat(v, f"{prefix}{k}."))
        return out
    return {prefix[:-1]: d}


#: cell.json's key listing the overrides its row was trained with (``catalogue.trained_overrides``; absent in
#: cells written before it was recorded, which are not compared on it)
OVERRIDES_KEY = "overrides"
#: an override's value where one side does not set its key, and where it deletes it (``~key``)
NOT_SET, DELETED = "(not set)", "(deleted)"


def override_values(overrides: Sequence[Any]) -> dict[str, str]:
    """Training overrides as key -> value as written (the last one wins, as Hydra's; ``~key``: ``DELETED``), the
    speed switches spelled under the ``speed`` node: two rows' definitions compared key by key."""
    out: dict[str, str] = {}
    for o in speed_node_spelling(overrides):
        out[override_key(o)] = DELETED if o.startswith("~") else o.partition("=")[2]
    return out


@dataclass(frozen=True)
class CellPin:
    """What a finished cell of a reproduction was made with: the dataset's hash, the weather family it drove
    (``family_known`` False: not known), the epochs it trained, its recipe (flat, ``model.lr`` -> value,
    all of it or only the keys known) and its row's training overrides (``override_values``: every key,
    ``trainer.*`` too). None: not known, not compared."""

    dataset: str | None = None
    weather_family: str | None = None
    family_known: bool = False
    epochs: int | None = None
    recipe: Mapping[str, Any] | None = None
    overrides: Mapping[str, str] | None = None


def pinned_recipe(train: Sequence[Any]) -> dict[str, Any]:
    """The recipe keys (flat) a folder's pinned training overrides set, with their values: the budget's
    overrides come after every row's, so each holds for every cell. Group choices and deletions set none."""
    parser, out = OverridesParser.create(), {}
    for o in train:
        try:
            ov = parser.parse_override(str(o))
        except HydraException:  # a pin this Hydra no longer reads sets nothing known here
            continue
        key = ov.key_or_group
        parts = key.split(".")
        if (ov.is_delete() or ov.is_sweep_override() or "/" in key or len(parts) < 2 or parts[0] not in RECIPE
                or (parts[0] == "data" and parts[1] in RECIPE_DATA_SKIP)):
            continue
        value = ov.value()
        if not (isinstance(value, str) and "${" in value):  # an interpolation: resolved where the cell composed
            out[key] = value
    return out


def pinned_epochs(train: Sequence[Any]) -> int | None:
    """The epochs a folder's pinned training overrides train (their last ``trainer.max_epochs=``), else None."""
    epochs = None
    for o in train:
        value = str(o).partition("=")[2]
        if override_key(o) == "trainer.max_epochs" and value.strip().isdigit():
            epochs = int(value)
    return epochs


def cell_mismatch(cell: Mapping[str, Any], pin: CellPin) -> tuple[str, Any, Any] | None:
    """The first of ``pin``'s keys a finished cell (its cell.json) records otherwise: (key, the cell's value,
    the pin's), else None. Only what both sides know is compared: a cell written before it recorded its
    dataset, family, recipe or overrides, and a recipe key only one side has (an option added later, whose default
    keeps the old behaviour), are no mismatch."""
    if cell.get("dataset") and pin.dataset and cell["dataset"] != pin.dataset:
        return "dataset", cell["dataset"], pin.dataset
    if pin.family_known and cell.get(FAMILY_KEY) is not None and cell[FAMILY_KEY] != pin.weather_family:
        return FAMILY_KEY, cell[FAMILY_KEY], pin.weather_family
    if pin.epochs is not None and cell.get("epochs") is not None and cell["epochs"] != pin.epochs:
        return "epochs", cell["epochs"], pin.epochs
    if pin.recipe and isinstance(cell.get("recipe"), dict):
        theirs = flat(cell["recipe"])
        for k in sorted(set(theirs) & set(pin.recipe)):
            if theirs[k] != pin.recipe[k]:
                return f"recipe.{k}", theirs[k], pin.recipe[k]
    if pin.overrides is not None and isinstance(cell.get(OVERRIDES_KEY), list):
        theirs = override_values(cell[OVERRIDES_KEY])  # every key either sets: set on one side alone differs
        for k in sorted(set(theirs) | set(pin.overrides)):
            if theirs.get(k, NOT_SET) != pin.overrides.get(k, NOT_SET):
                return f"{OVERRIDES_KEY}.{k}", theirs.get(k, NOT_SET), pin.overrides.get(k, NOT_SET)
    return None


def _shown(value: Any) -> str:
    return value if isinstance(value, str) else json.dumps(value)


def check_cell_pin(path: Path, cell: Mapping[str, Any], pin: CellPin, against: str, fix: str) -> None:
    """One error line naming the cell's file, the key and both values when ``cell_mismatch`` finds one: the
    one definition of "this cell belongs to this reproduction", for a run's finished cells (skipped) and for
    a report's (pooled). ``against``: whose value the second is ("this run makes row cil with")."""
    found = cell_mismatch(cell, pin)
    if found is not None:
        key, theirs, ours = found
        raise CicfwError(f"cell {str(path)!r} was made with {key}={_shown(theirs)}, {against} {key}={_shown(ours)}; "
                         f"{fix}", key=key, value=theirs)


def check_rows_agree(results_dir: Path, cells: Sequence[CellResult]) -> None:
    """The cells of each row were trained with the same overrides (``OVERRIDES_KEY``) and recipe
    (``check_one_recipe``), else one line naming a cell, the key and both values (``check_cell_pin``): a row
    redefined between runs would pool two setups as seeds of one. The first cell of a row that records them is
    the others' reference; cells that record none (written before) are not compared."""
    first: dict[str, CellResult] = {}
    for c in cells:
        if not isinstance(c.meta.get(OVERRIDES_KEY), list):
            continue
        ref = first.setdefault(c.row, c)
        if ref is not c:
            check_cell_pin(Path(results_dir) / "cells" / c.row / f"seed{c.seed}" / "cell.json", c.meta,
                           CellPin(overrides=override_values(ref.meta[OVERRIDES_KEY])),
                           f"cell {ref.row}/seed{ref.seed} of its row was made with",
                           "a row's cells must share its definition; keep one setup per row in a folder")
    check_one_recipe([(Path(results_dir) / "cells" / c.row / f"seed{c.seed}" / "cell.json", c) for c in cells])


def finished_cells(folder: Path) -> dict[str, dict[str, Any]]:
    """``row/seedK`` -> cell.json of every finished (status ok) cell under ``folder``."""
    out = {}
    for f in cell_files(folder):
        d = read_json(f, kind=dict)  # null (edited by hand): one line naming the file
        if d.get("status") == "ok":
            out[f"{f.parent.parent.name}/{f.parent.name}"] = d
    return out

