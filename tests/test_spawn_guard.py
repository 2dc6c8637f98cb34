"""Spawned workers import the script that started them again: a script without the
``if __name__ == "__main__":`` guard, or a call made while a worker imports it, is one line naming the
workers key, before any folder is locked or written."""
from __future__ import annotations

import multiprocessing as mp
from pathlib import Path
from types import SimpleNamespace

import pytest

from cicfw.core import spawning
from cicfw.core.errors import CicfwError

TOWN = str(Path(__file__).parent / "data" / "bench_town.yaml")


@pytest.mark.parametrize("text, guarded", [
    ("import x\nx.run()\n", False),
    ("import x\nif __name__ == '__main__':\n    x.run()\n", True),
    ('import x\nif "__main__" == __name__:\n    x.run()\n', True),
    ("def f():\n    if __name__ == '__main__':\n        pass\nf()\n", False),  # not at the top level
    ("if __name__ != '__main__':\n    pass\n", False),
    ("def (:\n", None),  # not Python: nothing is said
])
def test_a_script_guard_is_read_from_its_top_level(tmp_path, text, guarded):
    script = tmp_path / "s.py"
    script.write_text(text)
    assert spawning.script_has_guard(script) is guarded


def _started_by(monkeypatch, script: Path) -> None:
    """This process as if started by ``script`` (multiprocessing's own view is left as it is)."""
    monkeypatch.setattr(spawning, "spawn", SimpleNamespace(
        get_preparation_data=lambda name: {"init_main_from_path": str(script)}))


def test_an_unguarded_script_is_refused_naming_it_and_the_key(tmp_path, monkeypatch):
    script = tmp_path / "drive.py"
    script.write_text("from cicfw.benchmark.app import evaluate_policy\nevaluate_policy({}, {}, {}, 'out')\n")
    _started_by(monkeypatch, script)
    with pytest.raises(CicfwError) as err:
        spawning.check_spawn_safe("evaluate_policy", "runner.workers", 2)
    assert (err.value.key, err.value.value) == ("runner.workers", 2) and str(script) in str(err.value)
    script.write_text("if __name__ == '__main__':\n    pass\n")
    spawning.check_spawn_safe("evaluate_policy", "runner.workers", 2)  # guarded: passes


def test_a_call_while_a_worker_imports_the_script_is_refused(monkeypatch):
    monkeypatch.setattr(mp.current_process(), "_inheriting", True, raising=False)
    with pytest.raises(CicfwError) as err:
        spawning.check_spawn_safe("collect_dataset", "collect.workers", 2)
    assert err.value.key == "collect.workers"


def test_evaluate_policy_refuses_an_unguarded_script_before_writing(tmp_path, monkeypatch):
    from cicfw.benchmark.app import evaluate_policy

    script = tmp_path / "drive.py"
    script.write_text("evaluate_policy()\n")
    _started_by(monkeypatch, script)
    out = tmp_path / "eval"
    with pytest.raises(CicfwError) as err:
        evaluate_policy({"name": "expert"}, {"towns": [TOWN], "weathers": ["MidRainyNoon"], "training_towns": [],
                                            "pairs": [4, 13]}, {"workers": 2}, out, maps=False)
    assert (err.value.key, err.value.value) == ("runner.workers", 2)
    assert not (out / "episodes.jsonl").exists()


def test_collect_dataset_refuses_an_unguarded_script_before_locking(tmp_path, monkeypatch):
    from cicfw.collect import collect_dataset

    script = tmp_path / "collect.py"
    script.write_text("collect_dataset()\n")
    _started_by(monkeypatch, script)
    out = tmp_path / "data"
    with pytest.raises(CicfwError) as err:
        collect_dataset({"episodes": 2, "seconds": 1, "workers": 2, "weathers": ["ClearNoon"],
                         "cameras": ["centre"]}, out, progress=False)
    assert (err.value.key, err.value.value) == ("collect.workers", 2)
    assert not out.exists() or not any(out.iterdir())
