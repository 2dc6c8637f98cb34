"""Episodes in spawned worker processes, one backend each, that die with their parent."""
from __future__ import annotations

import ctypes
import os
import pickle
import signal
import sys
import threading
import time
import traceback
from multiprocessing import get_context
from multiprocessing.connection import Connection, wait
from pathlib import Path
from typing import Any, Callable

from cicfw.collect.config import close_backend, make_backend
from cicfw.collect.episode import ParentGone, run_episode
from cicfw.collect.errors import CollectError
from cicfw.collect.lock import FolderLock
from cicfw.core.errors import USER_ERRORS
from cicfw.core.spawning import refused_by_worker
from cicfw.registry import SIM_BACKENDS


def _die_with_parent(parent_pid: int) -> None:
    """SIGKILL this process when ``parent_pid`` dies: the kernel's PR_SET_PDEATHSIG on Linux, and a
    thread that polls the parent pid every second everywhere."""
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(1, int(signal.SIGKILL), 0, 0, 0)  # PR_SET_PDEATHSIG = 1
        except (OSError, AttributeError):
            pass
    if os.getppid() != parent_pid:  # the parent died before prctl
        os._exit(1)

    def watch() -> None:
        while True:
            time.sleep(1.0)
            if os.getppid() != parent_pid:
                os._exit(1)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


class _Channel:
    """A worker's end of its pipe to the parent: ``get`` its next episode, ``put`` a message. A pipe, not a
    spawn Queue: a Queue's named semaphores are unlinked only by finalizers, and the resource tracker
    warns (after the app's last line) of any it still holds when the collector exits."""

    def __init__(self, conn: Connection) -> None:
        self.conn = conn

    def get(self) -> Any:
        return self.conn.recv()

    def put(self, msg: Any) -> None:
        self.conn.send(msg)


def _worker_main(index: int, sim: dict, cfg: dict, out_dir: str, parent_pid: int, tasks: Any, results: Any) -> None:
    _die_with_parent(parent_pid)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C and ends its workers
    try:
        backend = make_backend(sim)
    except BaseException as err:
        results.put(("error", index, None, _portable(err), traceback.format_exc()))
        return
    try:
        while True:
            ep = tasks.get()
            if ep is None:
                return
            results.put(("start", index, ep["id"]))
            try:
                marker = run_episode(cfg, ep, Path(out_dir), backend, parent_pid=parent_pid)
            except ParentGone:
                os._exit(1)
            except BaseException as err:
                results.put(("error", index, ep["id"], _portable(err), traceback.format_exc()))
                return
            results.put(("done", index, marker))
    finally:
        close_backend(backend)


def _portable(err: BaseException) -> BaseException | None:
    """``err`` if it survives pickling (so the parent can raise the same user error), else None."""
    try:
        pickle.loads(pickle.dumps(err))
        return err
    except Exception:
        return None


def _worker_specs(cfg: dict, n: int) -> list[dict]:
    """The backend config of each of up to ``n`` workers (fewer where the backend has fewer servers)."""
    sim = dict(cfg["sim"])
    name = sim.get("name", "embedded")
    per_worker = getattr(SIM_BACKENDS.get(name), "worker_kwargs", None)
    specs = []
    for i in range(n):
        kw = {k: v for k, v in sim.items() if k != "name"}
        if per_worker is not None:
            kw = per_worker(kw, i)
            if kw is None:
                break
        specs.append({"name": name, **kw})
    return specs


def _raise_worker_error(msg: tuple) -> None:
    """A worker's failure: its user error as the same one line, anything else with its traceback."""
    _, i, ep_id, err, tb = msg
    if isinstance(err, USER_ERRORS):  # a user error (CollectError, TownError ...): the same one line
        raise err
    where = f" on episode {ep_id}" if ep_id else ""
    raise RuntimeError(f"collect worker {i} failed{where}:\n{tb}")


def _check_workers(procs: list, current: dict[int, str | None], left: int, asked: object = None) -> None:
    """A worker that died, or every worker gone with episodes left, is one error naming it."""
    for i, p in enumerate(procs):
        refused = refused_by_worker(p.exitcode, "collect_dataset", "collect.workers",
                                    len(procs) if asked is None else asked)
        if refused is not None:
            raise refused
        if p.exitcode not in (None, 0):
            raise CollectError(f"collect worker {i} (pid {p.pid}) died with exit code {p.exitcode} "
                               f"while collecting episode {current.get(i)}; rerun to resume")
    if all(p.exitcode is not None for p in procs):
        raise CollectError(f"every collect worker has exited with {left} episode(s) left; rerun to resume")


def _end_workers(procs: list, conns: list[Connection]) -> None:
    """End every worker still running (SIGTERM, then SIGKILL after 5 s) and close the parent's pipe ends."""
    for p in procs:
        if p.is_alive():
            p.terminate()
    for p in procs:
        p.join(5.0)
        if p.is_alive():
            p.kill()
            p.join(5.0)
    for conn in conns:
        conn.close()


def _send(conn: Connection, ep: dict | None) -> bool:
    """Give a worker its next episode (None: no more); False when its pipe is closed (it died)."""
    try:
        conn.send(ep)
        return True
    except OSError:
        return False


def run_workers(cfg: dict, todo: list[dict], out_dir: Path, n: int, on_marker: Callable[[dict], None],
                lock: FolderLock) -> None:
    """Collect ``todo`` in ``n`` spawned workers (fewer where the backend has fewer servers), calling
    ``on_marker`` as each episode finishes; a worker that dies or fails is one error naming it. Each worker
    has one pipe to the parent, which hands out the episodes one at a time as workers get free."""
    ctx = get_context("spawn")
    pending = iter(todo)
    procs, conns = [], []
    current: dict[int, str | None] = {}
    try:
        for i, spec in enumerate(_worker_specs(cfg, n)):
            parent_end, child_end = ctx.Pipe()
            chan = _Channel(child_end)
            procs.append(ctx.Process(target=_worker_main, args=(i, spec, cfg, str(out_dir), os.getpid(), chan, chan),
                                     name=f"cicfw-collect-{i}", daemon=True))
            conns.append(parent_end)
            procs[-1].start()
            child_end.close()
        lock.update(workers=[p.pid for p in procs])
        open_ = {conn: i for i, conn in enumerate(conns) if _send(conn, next(pending, None))}
        left = len(todo)
        while left:
            ready = wait(list(open_), timeout=0.5)
            if not ready:
                _check_workers(procs, current, left, cfg.get("workers"))
                continue
            for conn in ready:
                try:
                    msg = conn.recv()
                except (EOFError, OSError):  # the worker is gone: _check_workers says how
                    del open_[conn]
                    continue
                kind, i = msg[0], msg[1]
                if kind == "start":
                    current[i] = msg[2]
                elif kind == "done":
                    current[i] = None
                    left -= 1
                    on_marker(msg[2])
                    if not _send(conn, next(pending, None)):
                        del open_[conn]
                else:
                    _raise_worker_error(msg)
    finally:
        _end_workers(procs, conns)
