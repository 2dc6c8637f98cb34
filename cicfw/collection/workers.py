"""Episodes in spawned worker processes, one backend each, that die with their parent."""
from __future__ import annotations

import ctypes
import os
import queue
import signal
import sys
import threading
import time
import traceback
from multiprocessing import get_context
from pathlib import Path
from typing import Any, Callable

from cicfw.collection.config import close_backend, make_backend
from cicfw.collection.episode import ParentGone, run_episode
from cicfw.collection.errors import CollectError
from cicfw.collection.lock import FolderLock
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
    import pickle

    try:
        pickle.loads(pickle.dumps(err))
        return err
    except Exception:
        return None


def run_workers(cfg: dict, todo: list[dict], out_dir: Path, n: int, on_marker: Callable[[dict], None],
                lock: FolderLock) -> None:
    """Collect ``todo`` in ``n`` spawned workers (fewer where the backend has fewer servers), calling
    ``on_marker`` as each episode finishes; a worker that dies or fails is one error naming it."""
    ctx = get_context("spawn")
    tasks, results = ctx.Queue(), ctx.Queue()
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
    for ep in todo:
        tasks.put(ep)
    for _ in specs:
        tasks.put(None)
    procs = [ctx.Process(target=_worker_main, args=(i, s, cfg, str(out_dir), os.getpid(), tasks, results),
                         name=f"cicfw-collect-{i}", daemon=True) for i, s in enumerate(specs)]
    current: dict[int, str | None] = {}
    try:
        for p in procs:
            p.start()
        lock.update(workers=[p.pid for p in procs])
        left = len(todo)
        while left:
            try:
                msg = results.get(timeout=0.5)
            except queue.Empty:
                for i, p in enumerate(procs):
                    if p.exitcode not in (None, 0):
                        raise CollectError(f"collect worker {i} (pid {p.pid}) died with exit code {p.exitcode} "
                                           f"while collecting episode {current.get(i)}; rerun to resume")
                if all(p.exitcode is not None for p in procs):
                    raise CollectError(f"every collect worker has exited with {left} episode(s) left; rerun to resume")
                continue
            kind, i = msg[0], msg[1]
            if kind == "start":
                current[i] = msg[2]
            elif kind == "done":
                current[i] = None
                left -= 1
                on_marker(msg[2])
            else:
                _, _, ep_id, err, tb = msg
                if isinstance(err, ValueError):  # a user error (CollectError, TownError ...): the same one line
                    raise err
                where = f" on episode {ep_id}" if ep_id else ""
                raise RuntimeError(f"collect worker {i} failed{where}:\n{tb}")
    finally:
        for p in procs:
            if p.is_alive():
                p.terminate()
        for p in procs:
            p.join(5.0)
            if p.is_alive():
                p.kill()
                p.join(5.0)
        tasks.cancel_join_thread()
        results.cancel_join_thread()
