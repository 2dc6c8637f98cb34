"""Closed-loop evaluation speed and the expert's reference scores, printed.

    python bench/closed_loop.py                      # everything (about 10-15 minutes on 2 cores)
    python bench/closed_loop.py --skip-suite         # expert table + batched vs one-by-one only
    python bench/closed_loop.py --parts --episodes 48 --rounds 3 --threads 2
                                                     # [5] only: the runner against its parts (below)

1. The expert on the whole suite (both towns x the four paper weathers): success per table column.
2. The whole suite for one CIL-size checkpoint (an untrained CICModule with the CIL encoder,
   ``independent`` branches and the ``regression`` head, saved through a Lightning Trainer), with
   rendering and batched inference, timed. An untrained network drives badly and its episodes end
   early, so the default times it as a *competent* model: the network runs on every frame at full
   cost but the car is steered by the expert (``--steer model`` steers with the network instead).
3. Lockstep-batched vs one-by-one (each episode alone, batch-1 inference) on the same episodes, both
   in one process, and the network alone at batch 1 vs the batch size, to show where time goes.

5. ``--parts``: the runner against its parts, on the same episodes, in one process on the same threads,
   interleaved rounds (each figure the median over the rounds), frames per second of:
   - the whole runner (``benchmark.runner.run``: simulator + renderer + the network as the checkpoint
     policy runs it, BatchNorm folded + NHWC, in the runner's batches; expert-steered as in 2.);
   - the simulator and the runner alone (the expert policy on the same episodes: no camera, no network);
   - the renderer alone (the centre camera re-rendered at every pose the runner served, at its time);
   - the network alone on batches of the sizes the runner's calls had: eager (NCHW, BatchNorm unfolded,
     ``predict_steer``) and as the runner runs it (``Agent.act`` on uint8 NHWC frames);
   and the arithmetic limit beside them: this process's fp32 matmul GFLOP/s (bench/model_cost.py's
   ``matmul_gflops``) over the network's FLOP per frame forward (``count``): the frames/s no fp32 forward
   of this network can beat on these threads.

Timings on a shared machine are noisy: the load average is printed before and after.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from cicfw.benchmark.policy import POLICIES, Policy


def load() -> str:
    try:
        return "load average %.2f %.2f %.2f" % os.getloadavg()
    except OSError:
        return "load average unknown"


def make_checkpoint(folder: Path) -> Path:
    import lightning as L

    from cicfw.model.module import CICModule

    L.seed_everything(0)
    model = CICModule()  # CIL: cil encoder, independent branches, regression head
    trainer = L.Trainer(logger=False, enable_checkpointing=False, enable_progress_bar=False, max_epochs=0,
                        accelerator="cpu", enable_model_summary=False)
    trainer.strategy.connect(model)
    path = folder / "cil_untrained.ckpt"
    trainer.save_checkpoint(path)
    return path


@POLICIES.register("bench_expert_steered")  # top level: spawned workers re-import this script
class ExpertSteeredNetwork(Policy):
    """Runs the checkpoint's network on every observation (full inference cost) but returns the
    expert's steering, so episodes last as long as a competent model's. Timing only."""

    def __init__(self, checkpoint: str) -> None:
        from cicfw.benchmark.builtin_policies import CheckpointPolicy, ExpertPolicy

        self.net = CheckpointPolicy(checkpoint=checkpoint)
        self.expert = ExpertPolicy()
        self.cameras = self.net.cameras
        self.label = "CIL-size network, expert-steered"

    def reset(self, episodes):
        self.expert.reset(episodes)

    def act(self, obs):
        self.net.act(obs)
        return self.expert.act(obs)


def cells_line(rows) -> str:
    from cicfw.benchmark.evaluation_report import Run, summary

    s = summary(Run("x", rows))
    return ", ".join(f"{v['name']}: {v['rate']:.2f}% ({v['success']}/{v['episodes']})" for v in s["cells"].values())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--workers", type=int, default=2, help="processes for the whole-suite run")
    ap.add_argument("--batch-size", type=int, default=64)
    ap.add_argument("--compare", type=int, default=48, help="episodes for batched vs one-by-one")
    ap.add_argument("--steer", choices=("expert", "model"), default="expert",
                    help="who steers during the timed whole-suite run (the network always runs)")
    ap.add_argument("--skip-suite", action="store_true", help="skip the whole-suite checkpoint run")
    ap.add_argument("--threads", type=int, default=None, help="torch threads in this process (default: all cores)")
    ap.add_argument("--only-inference", action="store_true",
                    help="only [4]: the inference variants at the runner's batch size (1 thread, as each of 2 workers)")
    ap.add_argument("--parts", action="store_true",
                    help="only [5]: frames/s of the whole runner, the simulator, the renderer and the network alone, "
                         "on the same episodes, beside the arithmetic limit")
    ap.add_argument("--episodes", type=int, default=48, help="[5]: episodes, spread over the suite's cells")
    ap.add_argument("--rounds", type=int, default=3, help="[5]: interleaved rounds (the median is printed)")
    ap.add_argument("--matmul", type=int, default=2048, help="[5]: the N of the N x N fp32 matmul measuring GFLOP/s")
    args = ap.parse_args()

    import torch

    if args.threads:
        torch.set_num_threads(args.threads)

    from cicfw.benchmark.builtin_policies import CheckpointPolicy, ExpertPolicy
    from cicfw.benchmark.evaluation_report import Run, markdown_table
    from cicfw.benchmark.runner import RunnerConfig, run
    from cicfw.benchmark.suite import PAPER_WEATHERS, build_suite, make_backend

    print(f"closed-loop bench: {os.cpu_count()} cores, torch {torch.__version__}, {load()}")
    if args.only_inference:
        return inference_variants(args.batch_size, frames=None)
    if args.parts:
        return runner_parts(args.episodes, args.batch_size, args.rounds, args.matmul)
    sim = {"name": "embedded"}
    suite_frames = None  # set by the whole-suite run below, unless --skip-suite
    backend = make_backend(sim)
    episodes = build_suite(backend, ["town_a", "town_b"], PAPER_WEATHERS, training_towns=["town_a"])
    print(f"suite: {len(episodes)} episodes (town_a {sum(e.town == 'town_a' for e in episodes) // 4} pairs, "
          f"town_b {sum(e.town == 'town_b' for e in episodes) // 4} pairs, x {len(PAPER_WEATHERS)} weathers)")

    # 1. the expert, every cell
    t = time.perf_counter()
    res = run(episodes, ExpertPolicy(), backend, RunnerConfig(progress_bar=False))
    print(f"\n[1] expert on the whole suite: {time.perf_counter() - t:.1f} s, {res.steps} steps "
          f"(no rendering: the expert reads no camera)")
    print(markdown_table([Run("Expert", res.rows)]))
    print("expert per cell:", cells_line(res.rows))
    fails = [r for r in res.rows if not r["success"]]
    for r in fails[:10]:
        print(f"  expert failure: {r['key']} {r['route']} {r['reason']} at {r['time_s']} s")
    expert_steps = res.steps

    with tempfile.TemporaryDirectory() as tmp:
        ckpt = str(make_checkpoint(Path(tmp)))
        print(f"\ncheckpoint: untrained CIL-size CICModule, "
              f"{sum(p.numel() for p in CheckpointPolicy(checkpoint=ckpt).model.parameters()) / 1e6:.2f} M parameters")

        # 2. the whole suite with the checkpoint
        if not args.skip_suite:
            name = "bench_expert_steered" if args.steer == "expert" else "checkpoint"
            spec = {"name": name, "checkpoint": ckpt}
            cfg = RunnerConfig(batch_size=args.batch_size, workers=args.workers, progress_bar=True)
            print(f"\n[2] whole suite, checkpoint policy ({'expert' if args.steer == 'expert' else 'network'} "
                  f"steering), workers={cfg.workers}, batch {cfg.batch_size}, {load()}")
            t = time.perf_counter()
            res = run(episodes, spec, sim, cfg)
            wall = time.perf_counter() - t
            print(f"whole suite: {wall:.1f} s = {wall / 60:.2f} min for {len(episodes)} episodes, {res.steps} steps "
                  f"= {res.steps / wall:.0f} frames/s ({1e3 * wall / res.steps:.2f} ms/step overall), "
                  f"success {Run('x', res.rows).success_rate():.1f}%")
            suite_frames = res.steps
            worst = sum(int(np.ceil(r['timeout_s'] * 10)) for r in res.rows)
            print(f"  if every episode ran to its timeout ({worst} steps): ~{wall * worst / res.steps / 60:.1f} min "
                  f"at the same cost per step; {load()}")

        # 3. lockstep-batched vs one-by-one, same episodes, one process each
        sub = [e for k, e in enumerate(episodes) if k % max(len(episodes) // args.compare, 1) == 0][: args.compare]
        policy = ExpertSteeredNetwork(ckpt)
        cfg1 = RunnerConfig(batch_size=args.batch_size, progress_bar=False)
        print(f"\n[3] {len(sub)} episodes, one process ({torch.get_num_threads()} torch threads), {load()}")
        from cicfw.sim.env import get_renderer
        from cicfw.sim.town import load_town

        for town, weather in sorted({(e.town, e.weather) for e in sub}):  # bake outside the timings
            get_renderer(load_town(town), weather, cfg1.seed, ("centre",))
        run(sub[:2], policy, backend, cfg1)  # warm-up: weights paged in, thread pools started
        t, c = time.perf_counter(), time.process_time()
        batched = run(sub, policy, backend, cfg1)
        tb, cb = time.perf_counter() - t, time.process_time() - c
        t, c = time.perf_counter(), time.process_time()
        one_rows = []
        for e in sub:
            one_rows += run([e], policy, backend, RunnerConfig(batch_size=1, progress_bar=False)).rows
        to, co = time.perf_counter() - t, time.process_time() - c
        same = [(a["reason"], a["steps"]) for a in batched.rows] == [(b["reason"], b["steps"]) for b in one_rows]
        n = batched.steps
        print(f"lockstep batched (batch {args.batch_size}): wall {tb:.1f} s = {1e3 * tb / n:.2f} ms/step, "
              f"cpu {cb:.1f} s = {1e3 * cb / n:.2f} ms/step")
        print(f"one by one (batch 1):           wall {to:.1f} s = {1e3 * to / n:.2f} ms/step, "
              f"cpu {co:.1f} s = {1e3 * co / n:.2f} ms/step")
        print(f"speed-up: {to / tb:.2f}x wall, {co / cb:.2f}x cpu ({n} steps each; same episodes, same "
              f"outcomes: {same}); {load()}")

        # where the time goes: the network alone, and one render
        net = policy.net.model
        for b in (1, args.batch_size):
            x = torch.randint(0, 255, (b, 3, 88, 200), dtype=torch.uint8)
            s, c = torch.rand(b) * 30, torch.randint(0, 4, (b,))
            with torch.inference_mode():
                net.predict_steer(x, s, c)
                ts = []
                for _ in range(max(5, 256 // b)):
                    t = time.perf_counter()
                    net.predict_steer(x, s, c)
                    ts.append(time.perf_counter() - t)
            print(f"network alone, batch {b:3d}: {1e3 * statistics.median(ts) / b:.2f} ms/frame (median)")
        r = get_renderer(load_town("town_a"), "MidRainyNoon", 0, ("centre",))
        route = batched.trajectories[batched.rows[0]["key"]]
        ts = []
        for k in range(len(route["x"])):
            t = time.perf_counter()
            r.render(float(route["x"][k]), float(route["y"][k]), float(route["yaw"][k]), k * 0.1)
            ts.append(time.perf_counter() - t)
        print(f"render centre camera: {1e3 * statistics.median(ts):.2f} ms/frame (median); {load()}")
    print(f"\nexpert suite steps for reference: {expert_steps}")
    inference_variants(args.batch_size, frames=suite_frames or expert_steps)


def load_bench(name: str):
    """Another bench/ script as a module (bench/ is a folder of scripts, not a package)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, Path(__file__).with_name(f"{name}.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def spread(episodes: list, n: int) -> list:
    """``n`` episodes evenly spread over the suite (every cell gets its share)."""
    return [e for k, e in enumerate(episodes) if k % max(len(episodes) // max(n, 1), 1) == 0][:n]


def runner_parts(n_episodes: int, batch: int, rounds: int, matmul: int) -> None:
    """[5] Frames/s of the whole runner, the simulator + runner alone, the renderer alone and the network
    alone (eager, and as the runner runs it) on the same episodes, one process, the same threads,
    interleaved rounds; beside the arithmetic limit of an fp32 forward on these threads."""
    import cv2
    import torch

    from cicfw.benchmark.builtin_policies import ExpertPolicy
    from cicfw.benchmark.runner import RunnerConfig, run
    from cicfw.benchmark.suite import PAPER_WEATHERS, build_suite, make_backend, suite_routes
    from cicfw.model.checkpoint import load_model

    cost = load_bench("model_cost")
    cv2.setNumThreads(1)  # as each runner worker sets it
    backend = make_backend({"name": "embedded"})
    suite = build_suite(backend, ["town_a", "town_b"], PAPER_WEATHERS, training_towns=["town_a"])
    episodes = spread(suite, n_episodes)
    cfg = RunnerConfig(batch_size=batch, progress_bar=False)

    class Sized(ExpertSteeredNetwork):
        """The runner's policy, recording the size of every call."""

        sizes: list[int] = []

        def act(self, obs):
            self.sizes.append(len(obs))
            return super().act(obs)

    with tempfile.TemporaryDirectory() as tmp:
        ckpt = str(make_checkpoint(Path(tmp)))
        policy = Sized(ckpt)
        eager = load_model(ckpt)  # eval mode, NCHW, BatchNorm unfolded
        flop = cost.totals(cost.count(cost.build()))["forward_flop"]
        print(f"[5] the runner against its parts: {len(episodes)} episodes over "
              f"{len({(e.town, e.weather) for e in episodes})} (town, weather) cells, batch {batch}, one process, "
              f"{torch.get_num_threads()} torch threads, cv2 1 thread, {rounds} interleaved rounds; {load()}", flush=True)
        envs = {}
        for e in episodes:  # the renderers bake their textures outside the timings
            route = suite_routes(backend, e.town)[e.pair]
            envs[e.key] = backend.make_env(e.town, route, e.weather, seed=cfg.seed, cameras=("centre",))
        run(episodes[:2], policy, backend, cfg)  # warm-up: weights paged in, thread pools started
        rates: list[float] = []  # the matmul's GFLOP/s, measured in every round as the figures are

        figures: dict[str, list[float]] = {k: [] for k in (
            "whole runner (sim + renderer + network)", "simulator + runner alone (expert, no camera)",
            "renderer alone (centre camera)", "network alone, eager (NCHW, BatchNorm unfolded)",
            "network alone, as the runner runs it (folded + NHWC)")}
        names = list(figures)
        frames = 0
        for r in range(rounds):
            Sized.sizes = []
            t = time.perf_counter()
            res = run(episodes, policy, backend, cfg)
            figures[names[0]].append(res.steps / (time.perf_counter() - t))
            frames, sizes = res.steps, list(Sized.sizes)

            t = time.perf_counter()
            sim = run(episodes, ExpertPolicy(), backend, cfg)
            figures[names[1]].append(sim.steps / (time.perf_counter() - t))
            assert [row["steps"] for row in sim.rows] == [row["steps"] for row in res.rows]

            poses = [(envs[k].renderer, res.trajectories[k]) for k in (e.key for e in episodes)]
            t = time.perf_counter()
            n = 0
            for renderer, tr in poses:
                for k in range(len(tr["x"])):
                    renderer.render(float(tr["x"][k]), float(tr["y"][k]), float(tr["yaw"][k]), k * 0.1)
                    n += 1
            figures[names[2]].append(n / (time.perf_counter() - t))

            big = max(sizes)
            g = torch.Generator().manual_seed(r)
            x = torch.randint(0, 256, (big, 3, 88, 200), dtype=torch.uint8, generator=g)
            speed, cmd = torch.rand(big, generator=g) * 30, torch.arange(big) % 4
            frames_nhwc = x.permute(0, 2, 3, 1).contiguous().numpy()
            t = time.perf_counter()
            with torch.inference_mode():
                for b in sizes:
                    eager.predict_steer(x[:b], speed[:b], cmd[:b])
            figures[names[3]].append(sum(sizes) / (time.perf_counter() - t))
            agent = policy.net.agent
            speed_np, codes = speed.numpy(), (cmd + 2).numpy()
            t = time.perf_counter()
            for b in sizes:
                agent.act(frames_nhwc[:b], speed_np[:b], codes[:b])
            figures[names[4]].append(sum(sizes) / (time.perf_counter() - t))
            rates.append(cost.matmul_gflops(matmul))
            print(f"  round {r + 1}: " + ", ".join(f"{v[-1]:.0f}" for v in figures.values())
                  + f" frames/s; matmul {rates[-1]:.1f} GFLOP/s; {load()}", flush=True)

        gflops = statistics.median(rates)
        limit = gflops * 1e9 / flop
        print(f"\n{frames} frames per round ({len(sizes)} network calls, mean batch {frames / max(len(sizes), 1):.1f}); "
              f"medians over {rounds} rounds:")
        for i, (k, v) in enumerate(figures.items()):
            med = statistics.median(v)
            share = f"{100 * med / limit:5.1f}% of the limit" if i in (0, 3, 4) else "(no network)"
            print(f"  {k:<56} {med:8.1f} frames/s  {1e3 / med:7.2f} ms/frame  {share}")
        print(f"  {'arithmetic limit (fp32 forward at the matmul rate)':<56} {limit:8.1f} frames/s  {1e3 / limit:7.2f} ms/frame"
              f"  = {gflops:.1f} GFLOP/s ({matmul}x{matmul} fp32 matmul, {torch.get_num_threads()} threads, median) "
              f"/ {flop / 1e9:.3f} GFLOP a frame")
        whole, rend, net = (statistics.median(figures[names[i]]) for i in (0, 2, 4))
        print(f"  per frame: whole {1e3 / whole:.2f} ms = renderer {1e3 / rend:.2f} + network {1e3 / net:.2f} "
              f"+ the rest (simulator, runner, batching) {1e3 / whole - 1e3 / rend - 1e3 / net:.2f}; {load()}")
        print(f"SUMMARY runner {whole:.1f} frames/s, renderer {rend:.1f}, network (as run) {net:.1f}, "
              f"limit {limit:.1f} ({gflops:.1f} GFLOP/s, {torch.get_num_threads()} threads): runner / limit "
              f"{whole / limit:.3f}, network / limit {net / limit:.3f}")


def inference_variants(batch: int, frames: int | None, rounds: int = 5) -> None:
    """[4] The network alone at the runner's batch size with one torch thread (what each of the two
    workers has), interleaved rounds: eager, channels_last, BatchNorm folded + NHWC (what
    CheckpointPolicy runs), and that compiled, with its compilation time and whether it pays over
    ``frames`` frames (split over two workers, each compiling once)."""
    import torch

    from cicfw.model.checkpoint import prepare_for_inference
    from cicfw.model.module import CICModule
    from cicfw.model.speed import use_inductor_cache

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    base = CICModule().eval()

    def copy():
        m = CICModule().eval()
        m.load_state_dict(base.state_dict())
        return m

    x = torch.randint(0, 256, (batch, 3, 88, 200), dtype=torch.uint8)
    s, c = torch.rand(batch) * 30, torch.arange(batch) % 4
    models = {"eager": base, "channels_last": copy().use_channels_last(),
              "BN folded + NHWC (the policy)": prepare_for_inference(copy())}
    compiled = prepare_for_inference(copy())
    use_inductor_cache()
    t = time.perf_counter()
    compiled.forward = torch.compile(compiled.forward)
    with torch.inference_mode():
        compiled.predict_steer(x, s, c)
    compile_s = time.perf_counter() - t
    models["... + torch.compile"] = compiled
    with torch.inference_mode():
        ref = base.predict_steer(x, s, c)
        diffs = {k: (m.predict_steer(x, s, c) - ref).abs().max().item() for k, m in models.items()}
    times: dict[str, list[float]] = {k: [] for k in models}
    for _ in range(rounds):
        for k, m in models.items():
            with torch.inference_mode():
                ts = []
                for _ in range(5):
                    t = time.perf_counter()
                    m.predict_steer(x, s, c)
                    ts.append(time.perf_counter() - t)
            times[k].append(statistics.median(ts) / batch)
    print(f"\n[4] the network alone, batch {batch}, 1 torch thread, median of {rounds} interleaved rounds; {load()}")
    ms = {k: 1e3 * statistics.median(v) for k, v in times.items()}
    for k in models:
        print(f"  {k:<32} {ms[k]:6.2f} ms/frame   max |steer - eager's| {diffs[k]:.1e}")
    saved = (ms["BN folded + NHWC (the policy)"] - ms["... + torch.compile"]) / 1e3
    print(f"  torch.compile: {compile_s:.1f} s to compile (inductor cache {os.environ.get('TORCHINDUCTOR_CACHE_DIR')}), "
          f"saves {1e3 * saved:.2f} ms/frame; {load()}")
    if frames:
        per_worker = frames / 2
        print(f"  over {frames} suite frames (2 workers, each compiling once): {per_worker * saved:.1f} s saved vs "
              f"{compile_s:.1f} s compiling per worker -> {'pays' if per_worker * saved > compile_s else 'does not pay'}")
    torch.set_num_threads(threads)


if __name__ == "__main__":
    sys.exit(main())
