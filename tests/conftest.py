"""Shared fixtures: tiny datasets in the exact CIL HDF5 layout, composed configs, and the hand formulas
the statistics tests recompute with."""
from __future__ import annotations

import contextlib
import errno
import importlib.util
import io
import json
import logging
import math
import os
import re
import runpy
import signal
import subprocess
import sys
import traceback
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from hydra import compose, initialize_config_module

from cicfw.testing import make_targets, write_tiny_dataset  # noqa: F401  (tests import them from here)


def pytest_configure(config):
    """A suite started in the background (``nohup pytest ... &``) inherits SIGINT ignored, and so would the
    apps the Ctrl-C tests start, which would then never see their Ctrl-C: give them the default back.
    Under pytest-xdist, give each worker its share of the cores: two workers each running torch on
    every core (and the apps they start in subprocesses, which inherit OMP_NUM_THREADS) would fight."""
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT") or 0)
    if workers > 1:
        threads = max(1, (os.cpu_count() or 1) // workers)
        os.environ.setdefault("OMP_NUM_THREADS", str(threads))
        import torch

        torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))


def _parse_each_config_file_once() -> None:
    """Hydra parses every YAML file of a config tree again at each compose (the suite composes about 1,300
    times; the parse is a sixth of a compose). Keep each file's config as ``OmegaConf.load`` builds it from a
    fresh parse, keyed by its path, size and modification time, and hand out a deep copy of it (half the cost
    of building it again): the same config, and a file a test writes or edits is parsed anew."""
    import copy

    import yaml
    from omegaconf import OmegaConf
    from omegaconf._utils import get_yaml_loader

    load, parsed = OmegaConf.load, {}

    def cached_load(file_):
        name = getattr(file_, "name", None)
        if not isinstance(file_, io.TextIOBase) or not isinstance(name, str) or not os.path.isfile(name):
            return load(file_)
        st = os.stat(name)
        key = (name, st.st_size, st.st_mtime_ns)
        if key not in parsed:
            obj = yaml.load(file_, Loader=get_yaml_loader())
            if not isinstance(obj, (dict, list, type(None))):  # what load refuses or reads as a string
                file_.seek(0)
                return load(file_)
            parsed[key] = OmegaConf.create() if obj is None else OmegaConf.create(obj)
        return copy.deepcopy(parsed[key])

    OmegaConf.load = staticmethod(cached_load)


_parse_each_config_file_once()


def _share_the_config_store() -> None:
    """Each compose deep-copies its config repository, and with it the whole ``ConfigStore`` (every registered
    schema: a tenth of a compose), only so that re-reading the search path cannot change the original. Nothing
    in a compose writes to the store (a config loaded from it is a copy: ``ConfigStore.load``), so the copy
    may share it."""
    from hydra.core.config_store import ConfigStore

    ConfigStore.__deepcopy__ = lambda self, memo: self


_share_the_config_store()


@pytest.fixture(autouse=True)
def _no_log_handler_outlives_its_test():
    """An app run in-process (Hydra's job logging) hangs a handler on the root logger that writes to this
    test's captured stream, which pytest closes after it; a later test's log line would then print
    "--- Logging error ---" into that test's stderr. Take such handlers off when the test ends."""
    root = logging.getLogger()
    before = list(root.handlers)
    yield
    for handler in [h for h in root.handlers if h not in before and not type(h).__module__.startswith("_pytest")]:
        root.removeHandler(handler)
        handler.close()


def wilson(k: int, n: int, z: float) -> tuple[float, float]:
    """Wilson's score interval for k of n at normal quantile z, from its closed form (no library)."""
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return centre - half, centre + half


def mover(terms: list[tuple[float, int, int]], z: float) -> tuple[float, float]:
    """Zou & Donner's MOVER interval (points) of ``sum c * k / n`` over ``terms`` of ``(c, k, n)``, by hand
    from ``wilson``: the value less the root of the summed squared distances each term can pull it down (to
    Wilson's lower bound for c > 0, its upper for c < 0, times |c|), the upper bound the mirror."""
    value = down = up = 0.0
    for c, k, n in terms:
        p, (lo, hi) = k / n, wilson(k, n, z)
        value += c * p
        down += (c * (p - lo if c > 0 else hi - p)) ** 2
        up += (c * (hi - p if c > 0 else p - lo)) ** 2
    return 100 * (value - math.sqrt(down)), 100 * (value + math.sqrt(up))


def at(row: str, seed: int, pct: int, n: int = 100):
    """A reproduction cell with ``pct`` successes of ``n`` episodes in every column: overall ``pct``%."""
    from cicfw.reproduction.cells import COLUMNS, CellResult

    eps = {f"{c}/{k:03d}": {"success": k < pct, "column": c, "command": "left"} for c in COLUMNS for k in range(n)}
    return CellResult(row=row, seed=seed, episodes=eps, meta={"decoder": None, "wall_s": {}})


def pinned(row: str, seed: int, pct: int):
    """``at`` with 1,000 episodes a column (``pct`` x 10 successes): three seeds pool 3,000 a column, which pin
    a difference of two rows' overall to about ±1.3 points, so the episodes' floor stays inside the seeds'
    t-interval and a test's figures are the t-test's by hand (``seed_stats.with_episode_floor`` leaves them
    alone)."""
    return at(row, seed, pct * 10, n=1000)


def p_two_sided_2df(t: float) -> float:
    """Two-sided p of Student's t with 2 df, in closed form: 1 - |t| / sqrt(2 + t^2)."""
    return 1.0 - abs(t) / math.sqrt(2.0 + t * t)


@pytest.fixture
def tiny_data(tmp_path: Path) -> Path:
    return write_tiny_dataset(tmp_path / "data")


def compose_train(*overrides: str):
    with initialize_config_module("cicfw.conf", version_base="1.3"):
        return compose("train", overrides=list(overrides))


#: a training of a step or two on a tiny dataset, validated on one batch (``train_tiny_run``'s usual overrides)
TINY_TRAIN = ["data=cil_hdf5", "data.batch_size=8", "data.val_batch_size=8", "progress_bar=false", "speed.compile=false",
              "trainer.max_epochs=1", "trainer.limit_val_batches=1", "trainer.num_sanity_val_steps=0",
              "trainer.enable_model_summary=false"]


def train_tiny_run(root: Path, *overrides: str) -> dict:
    """A run of ``overrides`` on a tiny dataset under ``root``, its config saved in ``.hydra`` as the app
    leaves it (what resume checks read): its ``data``, ``run`` folder and ``last`` checkpoint."""
    from omegaconf import OmegaConf

    from cicfw.train.app import train

    data = write_tiny_dataset(root / "data", n_files=4, n=32)
    cfg = compose_train(*overrides, f"data.path={data}")
    run = root / "run"
    (run / ".hydra").mkdir(parents=True)
    OmegaConf.save(cfg, run / ".hydra" / "config.yaml")
    train(cfg, run, refuse_finished=True, claim=False)  # as the app, which claimed it before .hydra was written
    return {"data": data, "run": run, "last": run / "checkpoints" / "last.ckpt"}


@pytest.fixture
def fast_cfg(tiny_data: Path):
    """A train config on the tiny data: one fast_dev_run step, batch 8, no progress bar."""
    return compose_train(
        "data=cil_hdf5", f"data.path={tiny_data}", "data.batch_size=8", "data.val_batch_size=8",
        "debug=fast", "progress_bar=false",
    )


@pytest.fixture
def no_data(monkeypatch):
    """Fail loudly if training reaches the data (collecting or reading any file)."""
    import cicfw.train.app as train_mod
    from cicfw.data.datamodule import CILDataModule

    def touched(*_a, **_k):
        raise AssertionError("the data was touched before the config error was reported")

    monkeypatch.setattr(train_mod, "ensure_data", touched)
    monkeypatch.setattr(CILDataModule, "setup", touched)


def process_alive(pid: int) -> bool:
    """Running: not gone, and not a zombie waiting to be reaped (its new parent may not reap it at once)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state not in ("Z", "X")


@dataclass
class AppResult:
    """What ``run_app_in_process`` returns: the fields of ``subprocess.CompletedProcess`` a test reads."""

    returncode: int
    stdout: str
    stderr: str


def _logging_state() -> tuple:
    root = logging.getLogger()
    loggers = {name: (lg.level, list(lg.handlers), lg.propagate, lg.disabled)
               for name, lg in logging.Logger.manager.loggerDict.items() if isinstance(lg, logging.Logger)}
    return root.level, list(root.handlers), loggers, logging.root.manager.disable


def _restore_logging(state: tuple) -> None:
    level, handlers, loggers, disable = state
    root = logging.getLogger()
    for handler in [h for h in root.handlers if h not in handlers]:
        root.removeHandler(handler)
        handler.close()
    for handler in handlers:
        if handler not in root.handlers:
            root.addHandler(handler)
    root.setLevel(level)
    logging.disable(disable)
    for name, lg in list(logging.Logger.manager.loggerDict.items()):
        if not isinstance(lg, logging.Logger):
            continue
        if name in loggers:
            lg.level, kept, lg.propagate, lg.disabled = loggers[name]
            for handler in [h for h in lg.handlers if h not in kept]:
                lg.removeHandler(handler)
                handler.close()
        else:  # made by the app: keep the logger, drop what it hung on it
            for handler in list(lg.handlers):
                lg.removeHandler(handler)
                handler.close()


@contextlib.contextmanager
def _torch_state():
    torch = sys.modules.get("torch")
    if torch is None:
        yield
        return
    threads, rng = torch.get_num_threads(), torch.get_rng_state()
    precision, deterministic = torch.get_float32_matmul_precision(), torch.are_deterministic_algorithms_enabled()
    try:
        yield
    finally:
        torch.set_num_threads(threads)
        torch.set_rng_state(rng)
        torch.set_float32_matmul_precision(precision)
        torch.use_deterministic_algorithms(deterministic)


#: loggers Lightning gives a handler of their own (to stderr, not propagating) when imported where the root
#: logger has none, as in an app's process; under pytest the root has one, so they propagate instead
_OWN_HANDLER_LOGGERS = ("lightning.fabric", "lightning.pytorch")


def run_app_in_process(module: str, *args: str, cwd: str | os.PathLike | None = None,
                       env: dict[str, str | None] | None = None) -> AppResult:
    """``python -m <module> <args>`` run in this interpreter: its exit status, stdout and stderr, as
    ``subprocess.run(..., capture_output=True, text=True)`` gives them, without paying a fresh interpreter
    and the app's imports (seconds) for a test that only checks what an app refuses.

    ``env`` changes the environment for the run (a value of None removes the variable); ``cwd`` is the
    working directory. Everything the app changes in this process is put back afterwards: the arguments,
    working directory, environment, the signal handlers and ``sys.excepthook`` the app installs
    (``install_app_handlers``), logging (Hydra's job logging), warnings filters, torch's threads and
    random state, and Hydra's global state. An exception no app code caught goes to ``sys.excepthook``
    as in a process (an uncaught ``CicfwError`` is one ``cicfw: error:`` line, status 2; another keeps its
    traceback, status 1).

    Not for a test about the process itself (signals, exit of the interpreter, import side effects,
    umask, worker processes, the ``cicfw`` script): those start a subprocess."""
    import random

    import lightning.pytorch  # noqa: F401  (first, so that its loggers exist to be set as in a process)
    from hydra.core.global_hydra import GlobalHydra

    from cicfw.core import errors

    out, err = io.StringIO(), io.StringIO()
    saved_argv, saved_cwd, saved_env = list(sys.argv), os.getcwd(), dict(os.environ)
    saved_hook, saved_installed, saved_stopped = sys.excepthook, errors._installed, errors._stopped_by
    saved_signals = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)}
    saved_exit_now, saved_random = errors._exit_now, random.getstate()
    numpy = sys.modules.get("numpy")
    saved_np = numpy.random.get_state() if numpy is not None else None
    logging_state = _logging_state()

    def exit_now(status: int) -> None:  # the app's excepthook ends the process: here, the run
        raise SystemExit(status)

    code: object = 0
    try:
        errors._installed, errors._stopped_by, errors._exit_now = False, None, exit_now
        for key, value in (env or {}).items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = str(value)
        if cwd is not None:
            os.chdir(cwd)
        sys.argv = ["-m", *map(str, args)]
        if GlobalHydra.instance().is_initialized():
            GlobalHydra.instance().clear()
        for name in _OWN_HANDLER_LOGGERS:  # as a fresh import leaves them: their own handler, on stderr
            lg = logging.getLogger(name)
            lg.handlers, lg.propagate = [logging.StreamHandler(err)], False
        with _torch_state(), warnings.catch_warnings(), \
                contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                try:
                    runpy.run_module(module, run_name="__main__", alter_sys=True)
                except SystemExit:
                    raise
                except BaseException:
                    sys.excepthook(*sys.exc_info())  # the app's own hook may exit (SystemExit) from here
                    code = 1
            except SystemExit as exit_:
                code = exit_.code
            except BaseException:  # the hook itself failed: as the interpreter would, print it
                traceback.print_exc()
                code = 1
    finally:
        sys.excepthook, errors._installed, errors._stopped_by = saved_hook, saved_installed, saved_stopped
        errors._exit_now = saved_exit_now
        for sig, handler in saved_signals.items():
            signal.signal(sig, handler)
        sys.argv = saved_argv
        os.chdir(saved_cwd)
        os.environ.clear()
        os.environ.update(saved_env)
        if GlobalHydra.instance().is_initialized():
            GlobalHydra.instance().clear()
        _restore_logging(logging_state)
        random.setstate(saved_random)
        if saved_np is not None:
            numpy.random.set_state(saved_np)
    if code is None:
        status = 0
    elif isinstance(code, int):
        status = code
    else:  # sys.exit("message"): the message on stderr, status 1
        err.write(f"{code}\n")
        status = 1
    return AppResult(status, out.getvalue(), err.getvalue())


#: run in a fresh interpreter with a JSON {name: [module, *arguments]} as its argument: forks one child per
#: name, which runs ``python -m <module> <arguments>`` with its stdout and stderr in files; prints
#: {name: [status, out, err]}
_FORKS = r"""
import json, os, runpy, shutil, sys, tempfile, traceback

import lightning.pytorch, torch  # noqa: F401  (shared by the forks; no cicfw module, no Hydra config store)

assert not any(m == "cicfw" or m.startswith("cicfw.") for m in sys.modules)
folder, results = tempfile.mkdtemp(), {}
for name, argv in json.loads(sys.argv[1]).items():
    paths = [os.path.join(folder, f"{len(results)}.{s}") for s in ("out", "err")]
    pid = os.fork()
    if pid == 0:
        code = 1
        try:
            for fd, path in zip((1, 2), paths):
                os.dup2(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC), fd)
            sys.argv = list(argv)
            try:
                runpy.run_module(argv[0], run_name="__main__", alter_sys=True)
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
    results[name] = [status, *(open(p).read() for p in paths)]
shutil.rmtree(folder)
print(json.dumps(results))
"""


def run_apps_forked(runs: dict[str, list[str]], cwd: str | os.PathLike | None = None,
                    env: dict[str, str] | None = None, timeout: float = 600) -> dict[str, AppResult]:
    """Each ``python -m <module> <arguments>`` of ``runs`` (name -> [module, *arguments]) in a process of its
    own, as a user's shell starts it, for a test about what an app does at its start (its config store, its
    plugin scan). The processes are forks of one interpreter, started here, that has imported the third-party libraries every
    app imports first (torch, Lightning): each fork skips those imports (most of an app's start) and imports
    cicfw and its app itself, as a fresh process does."""
    run = subprocess.run([sys.executable, "-c", _FORKS, json.dumps(runs)], capture_output=True, text=True,
                         timeout=timeout, cwd=cwd, env=env)
    assert run.returncode == 0, run.stderr[-3000:]
    return {name: AppResult(*got) for name, got in json.loads(run.stdout).items()}


def load_bench_script(name: str):
    """A script of bench/ (not a package) imported as a module, so tests can call its functions."""
    path = Path(__file__).resolve().parents[1] / "bench" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def assert_refused(result: object, key: object, value: object = None, status: int = 2) -> str:
    """An app (``run_app_in_process``'s result, or a ``subprocess.CompletedProcess`` with text) refused its
    input as a user error: exit ``status`` (2), no traceback, and stderr ends with its one ``cicfw: error:``
    line, which names ``key`` and ``value`` (each as ``str``; None: not checked). Returns the line for a
    test that checks more. It asserts no sentence, so a reworded message keeps the test."""
    stderr = result.stderr
    lines = [line for line in stderr.splitlines() if line.startswith("cicfw: error:")]
    assert result.returncode == status, stderr[-3000:]
    assert len(lines) == 1 and "Traceback" not in stderr, stderr[-3000:]
    assert stderr.rstrip("\n").splitlines()[-1] == lines[0], stderr[-3000:]  # one line: nothing after it
    for part in (key, value):
        assert part is None or str(part) in lines[0], (part, lines[0])
    return lines[0]


def fill_the_disk_for_pictures(mp: pytest.MonkeyPatch) -> None:
    """cicfw's file writes (``cicfw.core.files.write_all``) fail with ENOSPC for a PNG's temporary file, as a
    disk that fills while a picture is written; every other file is written as usual. ``mp``: a monkeypatch."""
    import cicfw.core.files

    write_all = cicfw.core.files.write_all

    def full_for_pictures(fd, data):
        if ".png." in os.readlink(f"/proc/self/fd/{fd}"):
            raise OSError(errno.ENOSPC, "No space left on device")
        write_all(fd, data)

    mp.setattr(cicfw.core.files, "write_all", full_for_pictures)


def damaged_checkpoints(folder: Path) -> tuple[Any, dict[str, tuple[Path, tuple[int, int, int], str]]]:
    """A small ``CICModule`` (independent mixer, hidden 8) and checkpoints of it that Lightning can resume
    (optimizer and loop state) whose state_dict was edited under the same hyper_parameters: a weight deleted,
    one added, one of another shape, or a gtu mixer's weights. Each with its (missing, unexpected, reshaped)
    counts and the key a message names first, counted here by hand."""
    import torch

    from cicfw.model.module import CICModule

    model = CICModule(mixer_kwargs={"hidden": 8})
    state = model.state_dict()
    last = list(state)[-1]  # mixer.branches.3.6.bias
    extra = "mixer.extra.weight"
    wide = next(k for k in state if k.endswith(".weight") and state[k].dim() == 2)
    gtu = CICModule(mixer="gtu", mixer_kwargs={"hidden": 8}).state_dict()
    gtu_only = [k for k in gtu if k not in state]
    assert gtu_only and all(k in gtu for k in state)  # gtu adds weights, keeps the rest
    states = {
        "missing": ({k: v for k, v in state.items() if k != last}, (1, 0, 0), last),
        "unexpected": ({**state, extra: torch.zeros(2)}, (0, 1, 0), extra),
        "reshaped": ({**state, wide: torch.zeros(state[wide].shape[0] + 1, state[wide].shape[1])}, (0, 0, 1), wide),
        "other_mixer": (gtu, (0, len(gtu_only), 0), gtu_only[0]),
    }
    files = {}
    for name, (weights, counts, key) in states.items():
        path = Path(folder) / f"{name}.ckpt"
        torch.save({"state_dict": weights, "optimizer_states": [], "lr_schedulers": [], "loops": {}, "epoch": 0,
                    "global_step": 0, "hyper_parameters": dict(model.hparams)}, path)
        files[name] = (path, counts, key)
    return model, files


def misfit_counts(message: str) -> tuple[int, int, int]:
    """The (missing, unexpected, reshaped) weight counts a refused checkpoint's message gives."""
    found = re.search(r"(\d+) missing, (\d+) unexpected, (\d+) reshaped", message)
    assert found, message
    return tuple(int(n) for n in found.groups())
