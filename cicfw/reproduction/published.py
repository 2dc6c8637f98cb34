"""Published results folders (docs/results/<name>): copy a reproduction's small results there, and
continue one from a fresh clone (its finished cells copied back, so the launcher skips them)."""
from __future__ import annotations

from pathlib import Path
from typing import Any

from cicfw.core.errors import CicfwError
from cicfw.core.files import atomic_write, write_together
from cicfw.core.json_files import read_json
from cicfw.reproduction.cells import cell_files, cell_runs, finished_cells

#: a results folder's manifest, and a published folder's
MANIFEST = "reproduce.json"
#: what ``publish`` copies into a published folder besides cells/<row>/seed<k>/cell.json
PUBLISHED_FILES = ("RESULTS.md", "results.json", "results.csv", "results.png", "forest.png", "learning_curve.png",
                   MANIFEST)

def check_publish_outside(results_dir: str | Path, dest: str | Path, key: str) -> None:
    """A publish folder inside the results folder (a cell's folder, say) would put a published copy among
    the run's own cells and files: refused in one line naming ``key`` (links and ``..`` resolved)."""
    if Path(results_dir).expanduser().resolve() in Path(str(dest)).expanduser().resolve().parents:
        raise CicfwError(f"{key}={str(dest)!r} lies inside the results folder ({str(results_dir)!r}), among the run's "
                         f"own cells and files: give {key}=<a folder outside it> (e.g. docs/results/<budget>) or "
                         f"leave it out", key=key, value=str(dest))


def publish_target_manifest(dest: str | Path, key: str) -> dict[str, Any] | None:
    """The manifest of the folder ``publish`` would write into, or None where it holds none of what ``publish``
    writes (missing, empty): nothing there to keep. A reproduction's results folder (its cells hold their
    runs), or files of no reproduction (no manifest), would be replaced: refused in one line naming ``key``."""
    pub = Path(dest)
    if not pub.is_dir():
        return None
    held = [n for n in PUBLISHED_FILES if (pub / n).exists()] + (["cells/"] if (pub / "cells").is_dir() else [])
    if not held:
        return None
    where = f"{key}={str(pub)!r}"
    ran = cell_runs(pub)  # a published folder's cells hold their cell.json alone
    if ran:
        raise CicfwError(f"{where} is a reproduction's results folder, not a published one (its cells hold their "
                         f"runs: {', '.join(ran[:2])}{' ...' if len(ran) > 2 else ''}); publishing would replace its "
                         f"{MANIFEST}, report and cell.json files: give another {key}, or continue it "
                         f"with results_dir={str(pub)!r}", key=key, value=str(pub))
    if not (pub / MANIFEST).is_file():
        raise CicfwError(f"{where} holds {', '.join(held)} of no reproduction (no {MANIFEST}), which publishing "
                         f"would replace; give another {key}", key=key, value=str(pub))
    try:
        return published_manifest(pub)
    except CicfwError as err:
        raise CicfwError(str(err).replace("continue_from=", f"{key}=", 1), key=key, value=str(pub)) from None


def check_no_other_cells(dest: str | Path, results_dir: str | Path, held: set[str], key: str, fix: str) -> None:
    """One line naming ``key`` when the published folder ``dest`` holds a finished cell that is not among
    ``held`` (``row/seedK``: what the results folder holds or continues): publishing would replace its table
    with one that leaves that cell out, while the cell stays beside it. ``fix``: how to add to that folder."""
    others = sorted(set(finished_cells(Path(dest))) - set(held))
    if others:
        raise CicfwError(f"{key}={str(dest)!r} holds {len(others)} finished cell(s) of another reproduction "
                         f"({', '.join(others[:4])}{' ...' if len(others) > 4 else ''}) that results_dir="
                         f"{str(results_dir)!r} does not hold, so its published table would not be theirs; {fix}, "
                         f"or give another {key}", key=key, value=str(dest))


def check_publish_target(results_dir: str | Path, dest: str | Path, key: str, fix: str) -> None:
    """``dest`` is ``results_dir``'s to publish into (``publish_target_manifest``), and every finished cell it
    holds is one ``results_dir`` holds (``check_no_other_cells``), else one line naming ``key``, before anything
    is written. ``dest`` at ``results_dir`` itself replaces nothing and passes. ``fix``: how to add to that folder."""
    if Path(dest).resolve() == Path(results_dir).resolve():  # published onto itself: nothing is replaced
        return
    if publish_target_manifest(dest, key) is not None:
        held = set(finished_cells(Path(results_dir))) if Path(results_dir).is_dir() else set()
        check_no_other_cells(dest, results_dir, held, key, fix)


def publish(results_dir: Path, dest: Path) -> list[Path]:
    """Copy a reproduction's small results into ``dest`` (for committing): RESULTS.md, results.json/.csv,
    the pictures, the manifest and every cell's cell.json (never checkpoints or episode logs). All or none
    (``write_together``): a full disk leaves the earlier copy whole, never its report beside newer cells."""
    results_dir, dest = Path(results_dir), Path(dest)
    files = [results_dir / n for n in PUBLISHED_FILES if (results_dir / n).is_file()]
    files += cell_files(results_dir)
    if dest.exists() and not dest.is_dir():
        raise CicfwError(f"publish_dir {str(dest)!r} is a file, not a folder; give publish_dir=<a folder>")
    pairs = [(f, dest / f.relative_to(results_dir)) for f in files]
    copies = [(f, target) for f, target in pairs if target.resolve() != f.resolve()]

    def contents():  # one file's bytes in memory at a time
        for f, target in copies:
            target.parent.mkdir(parents=True, exist_ok=True)
            yield target, f.read_bytes()

    write_together(contents())
    return [target for _, target in pairs]


def published_manifest(src: Path) -> dict[str, Any]:
    """The manifest (``reproduce.json``) of a published results folder; a ValueError of one line saying what
    it is not."""
    src = Path(src)
    if not src.is_dir():
        raise CicfwError(f"continue_from={str(src)!r} is not a folder; give a published results folder "
                         f"(reproduce.json and cells/<row>/seed<k>/cell.json, e.g. docs/results/<budget>)")
    manifest = read_json(src / "reproduce.json", default=None, kind=dict)  # not JSON: one line naming the file
    if manifest is None:
        raise CicfwError(f"continue_from={str(src)!r} is not a published results folder (no reproduce.json); give "
                         f"the folder that holds reproduce.json and cells/<row>/seed<k>/cell.json")
    return manifest


def continue_published(src: Path, results_dir: Path, machine: str | None = None) -> dict[str, list[str]]:
    """Copy into ``results_dir`` every finished cell of the published results folder ``src`` (as ``publish``
    writes it, e.g. docs/results/<budget>) that ``results_dir`` lacks, so the launcher skips it and a fresh
    clone grows the same table. The caller has checked that ``src`` is pinned to the same budget, suite and
    dataset and that its cells were trained as this cicfw trains them (``cicfw.reproduce``). Never
    overwritten: a finished cell ``results_dir`` already has. Not copied: failed cells (they are retried)
    and, with ``machine``, cells whose ``machine`` does not contain that text (a table made within one kind
    of CPU: the same seed trains another model on another kind). Returns {"copied": [...], "kept": [...],
    "other_machine": [...]} (``row/seedK`` names)."""
    src, results_dir = Path(src), Path(results_dir)
    copied, kept, other = [], [], []
    have = finished_cells(results_dir)
    for name, cell in finished_cells(src).items():
        if machine is not None and machine not in str(cell.get("machine") or ""):
            other.append(name)
            continue
        if name in have:
            kept.append(name)
            continue
        rel = Path("cells", *name.split("/"), "cell.json")
        if (results_dir / rel).resolve() != (src / rel).resolve():
            atomic_write(results_dir / rel, (src / rel).read_bytes())
        copied.append(name)
    return {"copied": copied, "kept": kept, "other_machine": other}

