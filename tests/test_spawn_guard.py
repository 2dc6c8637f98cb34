"""Spawned workers import the script that started them again: a script without the
``if __name__ == "__main__":`` guard, or a call made while a worker imports it, is one line naming the
workers key, before any folder is locked or written."""
from __future__ import annotations

import multiprocessing as mp
import os
import subprocess
import sys
import types
from pathlib import Path
from types import SimpleNamespace

import pytest

from cicfw.core import spawning
from cicfw.core.errors import CicfwError

TOWN = str(Path(__file__).parent / "data" / "bench_town.yaml")
ROOT = Path(__file__).resolve().parents[1]


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


def test_a_call_while_a_worker_imports_the_script_exits_for_its_parent_to_say(monkeypatch):
    monkeypatch.setattr(mp.current_process(), "_inheriting", True, raising=False)
    with pytest.raises(SystemExit) as stop:
        spawning.check_spawn_safe("collect_dataset", "collect.workers", 2)
    assert stop.value.code == spawning.REFUSED_EXIT


def test_a_collect_worker_that_refused_is_one_error_naming_the_key():
    from cicfw.collect.workers import _check_workers

    procs = [SimpleNamespace(exitcode=None, pid=11), SimpleNamespace(exitcode=spawning.REFUSED_EXIT, pid=12)]
    with pytest.raises(CicfwError) as err:
        _check_workers(procs, {}, 2, 2)
    assert (err.value.key, err.value.value) == ("collect.workers", 2) and "rerun" not in str(err.value)


def test_python_c_starts_workers_as_before(monkeypatch):
    monkeypatch.setattr(spawning, "spawn", SimpleNamespace(get_preparation_data=lambda name: {}))
    spawning.check_spawn_safe("evaluate_policy", "runner.workers", 2)  # no script to import again: passes


SCRIPT = """from cicfw.core.errors import install_app_handlers
install_app_handlers()
from cicfw.benchmark.app import evaluate_policy
CALL = lambda: evaluate_policy({{"name": "expert"}}, {{"towns": [{town!r}], "weathers": ["MidRainyNoon"],
    "training_towns": [], "pairs": [4, 13]}}, {{"workers": 2, "threads": 1}}, {out!r}, maps=False,
    sim={{"name": "embedded", "route_before": 6, "max_deviation": 2}})
{body}
"""


def test_a_call_outside_the_guard_is_one_line_before_any_worker(tmp_path):
    out = tmp_path / "eval"
    script = tmp_path / "drive.py"
    script.write_text(SCRIPT.format(town=TOWN, out=str(out), body="CALL()\nif __name__ == '__main__':\n    pass"))
    env = {**os.environ, "PYTHONPATH": str(ROOT), "CICFW_CACHE": str(tmp_path / "cache")}
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env, cwd=tmp_path,
                          timeout=120)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, proc.stderr
    assert len(lines) == 1 and "runner.workers=2" in lines[0] and "line 7" in lines[0], proc.stderr
    assert not (out / "summary.json").exists()


def test_a_script_read_from_stdin_is_refused_before_any_worker(tmp_path, monkeypatch):
    stdin_main = types.ModuleType("__main__")  # what ``python -`` makes: a file name workers cannot import
    stdin_main.__file__, stdin_main.__spec__ = "<stdin>", None
    monkeypatch.setitem(sys.modules, "__main__", stdin_main)
    with pytest.raises(CicfwError) as err:
        spawning.check_spawn_safe("evaluate_policy", "runner.workers", 2)
    assert (err.value.key, err.value.value) == ("runner.workers", 2) and "<stdin>" in str(err.value)
