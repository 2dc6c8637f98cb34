"""Each app's ``--help`` lists the config groups that app reads (its defaults list and what its options'
defaults lists reach), not the other apps' groups nor the schemas' plumbing (``cicfw_schema/...``).

Each app runs as ``python -m <app> --help`` in a process of its own, as a user's shell starts it, so that
Hydra's config store holds that app's schemas only. The six processes are forked from one interpreter that
has imported the third-party libraries every app imports first (torch, Lightning): each fork skips those
imports (most of an app's start), and imports cicfw and its app itself, as a fresh process does."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

pytestmark = pytest.mark.slow  # starts the apps

#: module -> the groups its --help offers
GROUPS = {
    "cicfw.train": {"data", "debug", "encoder", "experiment", "head", "hparams_search", "launcher", "logger", "mixer",
                    "speed", "trainer"},
    "cicfw.evaluate": {"policy", "sim", "suite"},
    "cicfw.collect": {"sim"},
    "cicfw.export": set(),
    "cicfw.diagnose": set(),
    "cicfw.reproduce": {"budget", "launcher"},
}

#: run in a fresh interpreter with the modules as arguments: forks one child per module, which runs
#: ``python -m <module> --help`` with its stdout and stderr in files; prints {module: [status, out, err]}
FORKS = r"""
import json, os, runpy, sys, tempfile, traceback

import lightning.pytorch, torch  # noqa: F401  (shared by the forks; no cicfw module, no Hydra config store)

assert not any(m == "cicfw" or m.startswith("cicfw.") for m in sys.modules)
folder, results = tempfile.mkdtemp(), {}
for module in sys.argv[1:]:
    paths = [os.path.join(folder, f"{module}.{s}") for s in ("out", "err")]
    pid = os.fork()
    if pid == 0:
        code = 1
        try:
            for fd, path in zip((1, 2), paths):
                os.dup2(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC), fd)
            sys.argv = [module, "--help"]
            try:
                runpy.run_module(module, run_name="__main__", alter_sys=True)
                code = 0
            except SystemExit as exit_:
                code = exit_.code if isinstance(exit_.code, int) else int(exit_.code is not None)
            except BaseException:
                traceback.print_exc()
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(code)
    status = os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1])
    results[module] = [status, *(open(p).read() for p in paths)]
print(json.dumps(results))
"""


@pytest.fixture(scope="module")
def helps(tmp_path_factory) -> dict[str, subprocess.CompletedProcess]:
    """Every app's ``--help``, each from its own process (a fork of one interpreter started here)."""
    run = subprocess.run([sys.executable, "-c", FORKS, *GROUPS], capture_output=True, text=True, timeout=600,
                         cwd=tmp_path_factory.mktemp("help"))
    assert run.returncode == 0, run.stderr[-3000:]
    return {m: subprocess.CompletedProcess([m, "--help"], *got) for m, got in json.loads(run.stdout).items()}


@pytest.mark.parametrize("module", GROUPS)
def test_help_lists_the_groups_the_app_reads(module, helps):
    run = helps[module]
    assert run.returncode == 0, run.stderr[-2000:]
    section = run.stdout.split("== Configuration groups ==", 1)[1].split("== Config ==", 1)[0]
    offered = {line.split(":", 1)[0] for line in section.splitlines()[1:] if ": " in line and not line.startswith("(")}
    assert offered == GROUPS[module], section
    assert "cicfw_schema" not in run.stdout
    if module == "cicfw.train":  # the options too, a plugin's included where one is installed
        assert any(line.startswith("mixer: ") and "gtu" in line for line in section.splitlines()), section
