"""The loader at the public CoRL-2017 set's size: setup time, peak memory and samples/s per data mode.

    python bench/data_scale.py write /scratch/corl --files 3300          # the layout, random images (~35 GB)
    python bench/data_scale.py measure /scratch/corl [--modes auto,false,true] [--workers 0,2] [--batches 150]
    python bench/data_scale.py train /scratch/corl [--steps 300] [--workers 0] [Hydra overrides ...]

``write`` makes files as the public set has them (200 frames each, ``rgb`` uint8 chunked per image,
``targets`` float32 with 28 columns, the four commands, three cameras, a few negative speeds); the images
are random (incompressible, like JPEG-decoded camera frames to HDF5). ``measure`` runs each (mode,
workers) in a fresh process: the datamodule's setup, then ``--batches`` training batches (augmentation
on, batches of 120) after 10 of warm-up. ``train`` runs the README's command on the folder, capped at
``--steps`` training steps and 20 validation batches. Memory is the peak over the process and its
children (DataLoader workers, DDP ranks), as RSS summed (an upper bound: shared pages count in each
process) and PSS summed (shared pages split among the processes that map them), sampled every 0.2 s.
Each line carries the load average: a figure taken beside another job is not a figure.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

from cicfw.core.errors import CicfwError, ConfigError, report_user_errors

FRAMES_PER_FILE = 200


def write(folder: Path, files: int, seed: int) -> None:
    """CoRL-2017-layout files; a pool of random 200-frame blocks, each file a rolled copy of one (fast to
    write, still incompressible and different per file)."""
    import numpy as np

    from cicfw.data.cil_hdf5 import write_file
    from cicfw.testing import make_targets

    rng = np.random.default_rng(seed)
    pool = [rng.integers(0, 256, (FRAMES_PER_FILE, 88, 200, 3), dtype=np.uint8) for _ in range(8)]
    refuse_other_files(folder, pool, seed)
    folder.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    for i in range(files):
        path = folder / f"data_{i:05d}.h5"
        if path.exists():
            continue
        targets = make_targets(FRAMES_PER_FILE, rng)
        targets[rng.random(FRAMES_PER_FILE) < 0.002, 10] = -rng.uniform(0.1, 3.0)  # a car rolling backwards
        try:
            write_file(path, np.roll(pool[i % len(pool)], i, axis=0), targets)  # atomic: no torn file is left
        except OSError as err:  # a full disk, a file-size limit (ulimit -f)
            raise CicfwError(f"bench/data_scale.py write: cannot write {err.filename or path} ({err.strerror or err}) "
                             f"after {i} of {files} files; free some space or raise the limit, then run the same "
                             f"command: it keeps the files written so far", key="folder", value=str(folder)) from None
        if (i + 1) % 100 == 0:
            rate = (i + 1) * FRAMES_PER_FILE * 52_800 / (time.perf_counter() - start) / 1e6
            print(f"  {i + 1}/{files} files ({rate:.0f} MB/s)", flush=True)
    print(f"wrote {files} files x {FRAMES_PER_FILE} frames into {folder}")


def refuse_other_files(folder: Path, pool: list, seed: int) -> None:
    """``write`` skips the files it finds (a rerun finishes an earlier one), so a folder holding any file it
    did not write with this ``seed`` is refused before anything is written: real data (the public set's
    names are ``data_NNNNN.h5`` too) would get random files beside it. Ours: file i's first frame is pool
    block i's frame -i (``np.roll``); dot files are temporaries of a killed write."""
    import h5py
    import numpy as np

    if folder.exists() and not folder.is_dir():  # mkdir's FileExistsError would be a traceback
        raise ConfigError("folder", str(folder), f"a folder, new or one this command filled with --seed {seed} "
                          f"(this is a file)")
    for p in sorted(folder.iterdir()) if folder.is_dir() else []:
        if p.name.startswith("."):
            continue
        m = re.fullmatch(r"data_(\d{5})\.h5", p.name)
        try:
            i = int(m.group(1)) if m else -1
            with h5py.File(p, "r") as f:
                ours = i >= 0 and np.array_equal(f["rgb"][0], pool[i % len(pool)][-i % FRAMES_PER_FILE])
        except (OSError, KeyError):  # not HDF5, or no rgb: not ours either
            ours = False
        if not ours:
            raise ConfigError("folder", str(folder), f"a new folder or one this command filled with --seed {seed} "
                              f"({p.name} is not its file: random files would be written beside real data)")


def tree_memory(pid: int) -> tuple[int, int]:
    """(RSS, PSS) in bytes summed over ``pid`` and its descendants."""
    pids, rss, pss = [pid], 0, 0
    while pids:
        p = pids.pop()
        try:
            for task in os.listdir(f"/proc/{p}/task"):
                pids += [int(c) for c in Path(f"/proc/{p}/task/{task}/children").read_text().split()]
            for line in Path(f"/proc/{p}/smaps_rollup").read_text().splitlines():
                if line.startswith("Rss:"):
                    rss += int(line.split()[1]) * 1024
                elif line.startswith("Pss:"):
                    pss += int(line.split()[1]) * 1024
        except (OSError, ValueError):
            continue  # a process that ended while we looked
    return rss, pss


class PeakMemory:
    """Samples ``tree_memory(pid)`` in a thread until stopped; keeps the peaks."""

    def __init__(self, pid: int, every: float = 0.2) -> None:
        self.pid, self.every, self.rss, self.pss = pid, every, 0, 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            rss, pss = tree_memory(self.pid)
            self.rss, self.pss = max(self.rss, rss), max(self.pss, pss)
            self._stop.wait(self.every)

    def stop(self) -> "PeakMemory":
        self._stop.set()
        self._thread.join()
        return self


def child(folder: str, mode: str, workers: int, batches: int) -> None:
    """One measurement, in its own process: prints a JSON line."""
    import logging

    logging.basicConfig(level=logging.INFO, format="  %(message)s")
    from cicfw.data.datamodule import CILDataModule

    setting = {"true": True, "false": False}.get(mode, mode)
    peak = PeakMemory(os.getpid())
    t0 = time.perf_counter()
    dm = CILDataModule(folder, in_memory=setting, num_workers=workers)
    try:
        dm.setup()
    except ValueError as err:
        print(json.dumps({"mode": mode, "workers": workers, "refused": str(err)}))
        return
    setup_s = time.perf_counter() - t0
    it = iter(dm.train_dataloader())
    for _ in range(10):
        next(it)
    t1 = time.perf_counter()
    n = sum(len(next(it)["steer"]) for _ in range(batches))
    rate = n / (time.perf_counter() - t1)
    peak.stop()
    print(json.dumps({"mode": mode, "workers": workers, "streamed": dm.train_set.store.array is None,
                      "setup_s": setup_s, "samples_per_s": rate, "peak_rss_gb": peak.rss / 1e9,
                      "peak_pss_gb": peak.pss / 1e9, "load": os.getloadavg()[0]}))


def measure(args) -> None:
    print(f"bench/data_scale.py measure: {args.folder}, modes {args.modes}, workers {args.workers}, "
          f"{args.batches} batches of 120; {os.cpu_count()} cores; load {os.getloadavg()[0]:.2f} before", flush=True)
    for mode in args.modes.split(","):
        for workers in (int(w) for w in args.workers.split(",")):
            out = subprocess.run([sys.executable, __file__, "_child", str(args.folder), mode, str(workers),
                                  str(args.batches)], capture_output=True, text=True)
            if out.returncode:
                sys.exit(f"bench/data_scale.py: in_memory={mode} workers={workers} failed:\n{out.stderr[-3000:]}")
            r = json.loads(out.stdout.strip().splitlines()[-1])
            if "refused" in r:
                print(f"in_memory={mode:5} workers={workers}: refused before reading an image: {r['refused']}")
                continue
            print(f"in_memory={mode:5} workers={workers}: {'streamed' if r['streamed'] else 'in RAM':8}  setup "
                  f"{r['setup_s']:6.1f} s  {r['samples_per_s']:7.0f} samples/s  peak RSS {r['peak_rss_gb']:5.2f} GB "
                  f"(PSS {r['peak_pss_gb']:5.2f} GB)  load {r['load']:.2f}", flush=True)


def train(args) -> None:
    """The README's command on the folder, capped in steps; wall time, exit status and peak memory."""
    cmd = [sys.executable, "-m", "cicfw.train", "data=cil_hdf5", f"data.path={args.folder}",
           f"data.num_workers={args.workers}", f"trainer.max_steps={args.steps}", "trainer.limit_val_batches=20",
           f"hydra.run.dir={args.run_dir}", *args.overrides]
    print("bench/data_scale.py train:", " ".join(cmd[1:]), f"(load {os.getloadavg()[0]:.2f} before)", flush=True)
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    peak = PeakMemory(proc.pid, every=0.5)
    lines = [line for line in proc.stdout if "data:" in line or "error" in line.lower() or "Epoch" not in line]
    rc = proc.wait()
    peak.stop()
    for line in lines[-12:]:
        print("  " + line.rstrip()[:240])
    print(f"exit {rc}; {time.perf_counter() - t0:.0f} s; peak RSS {peak.rss / 1e9:.2f} GB summed over the process "
          f"tree (PSS {peak.pss / 1e9:.2f} GB); load {os.getloadavg()[0]:.2f} after")
    if rc:  # the training's failure is the bench's: a caller reading the exit status must not see success
        sys.exit(rc)


@report_user_errors
def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "_child":
        return child(sys.argv[2], sys.argv[3], int(sys.argv[4]), int(sys.argv[5]))
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="what", required=True)
    w = sub.add_parser("write")
    w.add_argument("folder", type=Path)
    w.add_argument("--files", type=int, default=3300)
    w.add_argument("--seed", type=int, default=0)
    m = sub.add_parser("measure")
    m.add_argument("folder", type=Path)
    m.add_argument("--modes", default="auto,false,true")
    m.add_argument("--workers", default="0,2")
    m.add_argument("--batches", type=int, default=150)
    t = sub.add_parser("train")
    t.add_argument("folder", type=Path)
    t.add_argument("--steps", type=int, default=300)
    t.add_argument("--workers", type=int, default=0)
    t.add_argument("--run-dir", default="outputs/bench_data_scale")
    t.add_argument("overrides", nargs="*")
    args, extra = ap.parse_known_args()  # Hydra overrides may follow the options
    if extra and args.what != "train":
        ap.error(f"unrecognized arguments: {' '.join(extra)}")
    if args.what == "train":
        args.overrides = [*args.overrides, *extra]
    {"write": lambda: write(args.folder, args.files, args.seed), "measure": lambda: measure(args),
     "train": lambda: train(args)}[args.what]()


if __name__ == "__main__":
    main()
