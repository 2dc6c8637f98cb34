"""Inference latency per frame and peak memory of each way to run one model, printed.

    python bench/export_latency.py            # CIL-size model, batch 1 and 64, 1 and 2 threads (a few minutes)
    python bench/export_latency.py --quick    # the same table from a few calls each: shows it works, not a figure
    python bench/export_latency.py --checkpoint outputs/<run>/checkpoints/<best>.ckpt

Runtimes, each measured in its own process (so its peak memory, ``VmHWM``, is its own):

- ``torch eager``: ``CICModule.predict_steer`` as trained (BatchNorm and Dropout modules, NCHW);
- ``policy (torch, fused)``: the suite's checkpoint policy today, ``Agent.load(ckpt)`` (BatchNorm folded, NHWC);
- ``torchscript``: the ``cicfw export format=torchscript`` file through ``Agent``;
- ``onnxruntime``: the ``cicfw export format=onnx`` file through ``Agent``;
- ``onnxruntime, numpy only``: the same file in a process that never imports torch or cicfw
  (docs/deploy.md's loop): what a deployment without cicfw costs in memory.

Each row also gives the largest steering difference from ``torch eager`` on the same 64 inputs; a runtime
beyond the export's tolerance is not a candidate. The suite runs one worker per core with one torch thread
each and 64 episodes per call (conf/evaluate.yaml ``runner``), so its figure is batch 64 at 1 thread.
Latency is only a figure on a quiet machine: the load average is printed before and after.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

#: runtime name -> what the table calls it
RUNTIMES = {
    "eager": "torch eager",
    "policy": "policy (torch, fused)",
    "torchscript": "torchscript",
    "onnxruntime": "onnxruntime",
    "ort-numpy": "onnxruntime, numpy only",
}
#: batch size whose steering is compared across runtimes
CHECK_BATCH = 64


def load() -> str:
    try:
        return "load average %.2f %.2f %.2f" % os.getloadavg()
    except OSError:
        return "load average unknown"


def status_mb(field: str) -> float:
    """A memory figure of this process from /proc/self/status in MB (``VmRSS``: now, ``VmHWM``: its peak;
    both start afresh at exec, unlike ``ru_maxrss``, which a child inherits from the process that forked it)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 if field == "VmHWM" else 0.0


def inputs(batch: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``batch`` random frames, speeds and command codes, the same in every process."""
    rng = np.random.default_rng(seed)
    return (rng.integers(0, 256, (batch, 88, 200, 3), dtype=np.uint8), rng.uniform(0, 60, batch).astype(np.float32),
            (np.arange(batch) % 4 + 2).astype(np.int64))


# ---- one measurement, in its own process ---------------------------------------------------------
def runner(runtime: str, model: str, threads: int):
    """A function (images, speed, command) -> steering for ``runtime``, and the memory after its imports."""
    if runtime == "ort-numpy":  # nothing of torch or cicfw: the deployment's own footprint
        import onnxruntime as ort

        base = status_mb("VmRSS")
        opts = ort.SessionOptions()
        opts.intra_op_num_threads, opts.inter_op_num_threads = threads, 1
        session = ort.InferenceSession(model, opts, providers=["CPUExecutionProvider"])
        return (lambda img, speed, cmd: session.run(["steer"], {"images": img, "speed_kmh": speed,
                                                              "command": cmd})[0]), base
    from cicfw.export.agent import Agent

    base = status_mb("VmRSS")
    agent = Agent.load(model, threads=threads, device="cpu", fuse=runtime != "eager")
    return agent.act, base


def worker(runtime: str, model: str, batch: int, threads: int, warmup: int, reps: int, min_s: float) -> dict:
    """Time ``reps`` calls (at least ``min_s`` seconds) at ``batch`` after ``warmup`` calls; the median per frame."""
    run, base = runner(runtime, model, threads)
    img, speed, cmd = inputs(batch)
    for _ in range(warmup):
        run(img, speed, cmd)
    times: list[float] = []
    start = time.perf_counter()
    while len(times) < reps or time.perf_counter() - start < min_s:
        t0 = time.perf_counter()
        run(img, speed, cmd)
        times.append(time.perf_counter() - t0)
    steer = np.asarray(run(*inputs(CHECK_BATCH, seed=1)), np.float64).reshape(-1)
    return {"ms_per_frame": 1e3 * statistics.median(times) / batch, "calls": len(times),
            "imports_mb": base, "peak_mb": status_mb("VmHWM"),
            "steer": steer.tolist()}


def measure(runtime: str, model: Path, batch: int, threads: int, args: argparse.Namespace) -> dict:
    """``worker`` in a fresh process (its own peak memory, its own thread pool)."""
    cmd = [sys.executable, __file__, "--worker", runtime, "--model", str(model), "--batch", str(batch),
           "--threads", str(threads), "--warmup", str(args.warmup), "--reps", str(args.reps), "--min-s", str(args.min_s)]
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        tail = (res.stderr.strip().splitlines() or ["no output"])[-1]
        raise SystemExit(f"{RUNTIMES[runtime]} (batch {batch}, {threads} threads) failed: {tail}")
    return json.loads(res.stdout.strip().splitlines()[-1])


# ---- the table -----------------------------------------------------------------------------------
def cil_checkpoint(folder: Path, mixer: str, head: str) -> Path:
    """A CIL-size CICModule (untrained: latency does not depend on the weights), saved as a checkpoint."""
    import lightning as L
    import torch

    from cicfw.model.module import CICModule

    torch.manual_seed(0)
    model = CICModule(mixer=mixer, head=head)
    path = folder / f"{mixer}-{head}.ckpt"
    torch.save({"state_dict": model.state_dict(), "hyper_parameters": dict(model.hparams),
                "pytorch-lightning_version": L.__version__, "epoch": 0, "global_step": 0}, path)
    return path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--checkpoint", help="a cicfw checkpoint (default: an untrained CIL-size model)")
    ap.add_argument("--mixer", default="independent")
    ap.add_argument("--head", default="regression")
    ap.add_argument("--batches", default="1,64")
    ap.add_argument("--threads-list", default="1,2", help="threads for every runtime")
    ap.add_argument("--quick", action="store_true", help="a few calls each: shows the script works, not a figure")
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--reps", type=int, default=20)
    ap.add_argument("--min-s", type=float, default=3.0, help="time each runtime at least this long")
    # one measurement (what the parent runs in a subprocess)
    ap.add_argument("--worker", choices=list(RUNTIMES), help=argparse.SUPPRESS)
    ap.add_argument("--model", help=argparse.SUPPRESS)
    ap.add_argument("--batch", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--threads", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        print(json.dumps(worker(args.worker, args.model, args.batch, args.threads, args.warmup, args.reps, args.min_s)))
        return
    if args.quick:
        args.warmup, args.reps, args.min_s = 1, 2, 0.0

    from cicfw.export.app import TOLERANCE, export_model

    batches = [int(b) for b in args.batches.split(",")]
    threads_list = [int(t) for t in args.threads_list.split(",")]
    print(f"before: {load()}; {os.cpu_count()} cores{'; --quick: a few calls each, NOT a figure' if args.quick else ''}")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        ckpt = Path(args.checkpoint) if args.checkpoint else cil_checkpoint(folder, args.mixer, args.head)
        exported = {}
        for fmt, suffix in (("torchscript", ".pt"), ("onnx", ".onnx")):
            exported[fmt] = folder / f"model{suffix}"
            info = export_model(ckpt, fmt, exported[fmt], n_frames=2)
            print(f"exported {fmt}: {info['size_bytes'] / 1e6:.1f} MB, {info['label']}, parity "
                  f"{info['parity']['max_abs_diff']:.2g}")
        files = {"eager": ckpt, "policy": ckpt, "torchscript": exported["torchscript"],
                 "onnxruntime": exported["onnx"], "ort-numpy": exported["onnx"]}
        rows = []
        for runtime, model in files.items():
            for threads in threads_list:
                cells = {b: measure(runtime, model, b, threads, args) for b in batches}
                rows.append((runtime, threads, cells))
                print(f"  measured {RUNTIMES[runtime]}, {threads} thread(s)", flush=True)
    ref = {t: np.array(c[batches[-1]]["steer"]) for r, t, c in rows if r == "eager"}
    print(f"\nafter: {load()}\n")
    head = f"{'runtime':<25} {'threads':>7} " + " ".join(f"{f'batch {b} ms/frame':>18} {'peak MB':>8}" for b in batches)
    print(head + f" {'imports MB':>10} {'max|diff| vs eager':>19}")
    best = None
    for runtime, threads, cells in rows:
        diff = float(np.abs(np.array(cells[batches[-1]]["steer"]) - ref[threads]).max())
        line = f"{RUNTIMES[runtime]:<25} {threads:>7} " + " ".join(
            f"{cells[b]['ms_per_frame']:>18.3f} {cells[b]['peak_mb']:>8.0f}" for b in batches)
        print(line + f" {cells[batches[-1]]['imports_mb']:>10.0f} {diff:>19.2g}")
        ms = cells[batches[-1]]["ms_per_frame"]
        if threads == min(threads_list) and diff <= TOLERANCE and (best is None or ms < best[1]):
            best = (runtime, ms)
    if best:
        print(f"\nfastest correct runtime at batch {batches[-1]}, {min(threads_list)} thread (the suite's per-worker "
              f"setting): {RUNTIMES[best[0]]} ({best[1]:.3f} ms/frame)"
              + ("; --quick: not a figure, rerun without it on a quiet machine" if args.quick else ""))


if __name__ == "__main__":
    main()
