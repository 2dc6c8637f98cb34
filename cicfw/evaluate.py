"""``python -m cicfw.evaluate``: the paper's closed-loop single-turn suite for a checkpoint or a policy.

    python -m cicfw.evaluate checkpoint=outputs/<run>/checkpoints/<best>.ckpt
    python -m cicfw.evaluate policy=expert suite.towns=[town_b]
    python -m cicfw.evaluate -m checkpoint=a.ckpt,b.ckpt        # one joined table in the sweep folder

Writes the episode rows (JSON + CSV), the paper's table (Markdown + LaTeX), a map per town with the
driven paths and a bar chart into the run folder, and returns the overall success rate (%) so sweepers
can use it. ``evaluate_checkpoint`` runs the same from Python (``cicfw train evaluate_after=true``).
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Sequence

import hydra
from omegaconf import DictConfig, OmegaConf

from cicfw.bench.runs import load_trajectories, save_trajectories  # noqa: F401  (used here; importable from here)
from cicfw.errors import report_user_errors

log = logging.getLogger("cicfw.evaluate")


def policy_spec(cfg: DictConfig) -> dict[str, Any]:
    """The policy's plain config (``name:`` + kwargs), with the row label from ``name=`` if given."""
    spec = OmegaConf.to_container(cfg.policy, resolve=True)
    assert isinstance(spec, dict)
    if cfg.get("checkpoint") and spec.get("name") != "checkpoint":
        raise ValueError(f"checkpoint= is only read by policy=checkpoint, but policy={spec.get('name')}; "
                         f"drop checkpoint= or use policy=checkpoint")
    if spec.get("name") == "checkpoint" and not spec.get("checkpoint"):
        raise ValueError("no checkpoint to evaluate: give checkpoint=path/to.ckpt (written by cicfw train), "
                         "or policy=expert for the reference driver")
    if cfg.get("name"):
        spec["label"] = str(cfg.name)
    return spec


def evaluate(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """Run the suite described by ``cfg`` (conf/evaluate.yaml), write the report into ``run_dir``,
    return the summary (overall ``success`` % and per-column ``cells``)."""
    from cicfw.bench.policy import make_policy
    from cicfw.bench.report import Run, markdown_table, write_run
    from cicfw.bench.runner import RunnerConfig, run
    from cicfw.bench.suite import build_suite, make_backend
    from cicfw.bench.video import select_episodes

    run_dir = Path(run_dir)
    spec = policy_spec(cfg)
    sim = OmegaConf.to_container(cfg.sim, resolve=True)
    runner_cfg = RunnerConfig(**OmegaConf.to_container(cfg.runner, resolve=True), seed=int(cfg.seed),
                              progress_bar=bool(cfg.get("progress_bar", True)))
    policy = make_policy(spec)  # a bad checkpoint fails here, before any driving
    backend = make_backend(sim)
    suite = OmegaConf.to_container(cfg.suite, resolve=True)
    episodes = build_suite(backend, **suite)  # unknown towns and weathers fail here
    label = str(cfg.name) if cfg.get("name") else policy.label
    log.info("evaluating %s on %d episodes (%s x %s)", label, len(episodes), ", ".join(suite["towns"]),
             ", ".join(suite["weathers"]))
    if runner_cfg.resolve_workers(episodes, bool(policy.cameras)) > 1:
        del policy  # each worker process builds its own from the spec
        policy = spec
    res = run(episodes, policy, sim, runner_cfg, label=label)
    meta = {"policy": spec["name"], "checkpoint": spec.get("checkpoint"), "seed": int(cfg.seed),
            "suite": suite, "runner": OmegaConf.to_container(cfg.runner, resolve=True), "sim": sim,
            "wall_s": round(res.wall_s, 2), "steps": res.steps}
    report = Run(label=label, rows=res.rows, meta=meta, path=run_dir)
    summary = write_run(run_dir, report)
    save_trajectories(run_dir / "trajectories.npz", res.rows, res.trajectories)
    pictures(cfg, report, res.trajectories, run_dir, select_episodes(res.rows, list(cfg.get("video") or []),
                                                                     int(cfg.get("video_max", 8))))
    log.info("%d episodes in %.1f s (%d steps)\n%s", len(res.rows), res.wall_s, res.steps, markdown_table([report]))
    log.info("success %.2f%%; report in %s", summary["success"], run_dir)
    join_sweep()
    return summary


def pictures(cfg: DictConfig, report, trajectories: dict, run_dir: Path, filmed: Sequence[dict]) -> None:
    """The map per town, the bar chart, and the requested videos."""
    from cicfw.bench.plots import bar_chart, town_maps

    from cicfw.bench.suite import town_label

    towns = {town_label(t): str(t) for t in cfg.suite.towns}
    if cfg.get("maps", True):
        town_maps(report, trajectories, run_dir, towns)
    bar_chart([report], run_dir / "success_bars.png")
    if filmed:
        from cicfw.bench.video import write_video
        from cicfw.sim.town import load_town

        if cfg.sim.name != "embedded":
            log.warning("videos are re-rendered with the embedded simulator; sim=%s has none", cfg.sim.name)
            return
        for r in filmed:
            path = run_dir / "videos" / f"{r['key'].replace('/', '_')}.mp4"
            write_video(path, r, trajectories[r["key"]], load_town(towns[r["town"]]), r["weather"], int(cfg.seed))
            log.info("video: %s", path)


def join_sweep() -> None:
    """In a multirun, join every finished run of the sweep into one table in the sweep folder."""
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        if not HydraConfig.initialized() or HydraConfig.get().mode != RunMode.MULTIRUN:
            return
        if HydraConfig.get().job.config_name != "evaluate":  # e.g. reproduce's cells: that app reports itself
            return
        sweep_dir = Path(HydraConfig.get().sweep.dir)
    except Exception:
        return
    from cicfw.bench.report import find_runs, write_joined

    runs = find_runs([sweep_dir])
    write_joined(runs, sweep_dir)
    log.info("joined %d run(s) of the sweep into %s", len(runs), sweep_dir / "table.md")


def compose_config(overrides: Sequence[str] = ()) -> DictConfig:
    """conf/evaluate.yaml with ``overrides``, from inside or outside a running Hydra app."""
    from hydra import compose, initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    if GlobalHydra.instance().is_initialized():
        return compose("evaluate", overrides=list(overrides))
    with initialize_config_module("cicfw.conf", version_base="1.3"):
        return compose("evaluate", overrides=list(overrides))


def evaluate_checkpoint(checkpoint: str | Path, run_dir: str | Path, overrides: Sequence[str] = ()) -> dict[str, Any]:
    """The suite for one checkpoint, configured by conf/evaluate.yaml plus ``overrides``."""
    cfg = compose_config([f"checkpoint={_quote(str(checkpoint))}", *overrides])
    return evaluate(cfg, Path(run_dir))


def evaluate_after_training(cfg: DictConfig, trainer: Any, run_dir: Path) -> dict[str, Any]:
    """``cicfw train evaluate_after=true``: the suite on the run's best checkpoint (else its last one,
    else the final weights saved now), into ``<run_dir>/evaluate``. Logs ``closed_loop/success`` and
    one ``closed_loop/success/<cell>`` per table column to the trainer's logger and to the job's
    ``metrics.json`` (the sweep summary's ``closed_loop_success`` column); returns the summary."""
    run_dir = Path(run_dir)
    cb = trainer.checkpoint_callback
    path = (cb.best_model_path or cb.last_model_path) if cb is not None else ""
    if not path or not Path(path).is_file():
        path = str(run_dir / "checkpoints" / "final.ckpt")
        trainer.save_checkpoint(path)
    log.info("closed-loop evaluation of %s", path)
    summary = evaluate_checkpoint(path, run_dir / "evaluate", list(cfg.get("evaluate_overrides") or []))
    metrics = {"closed_loop/success": summary["success"],
               **{f"closed_loop/success/{k}": v["rate"] for k, v in summary["cells"].items()}}
    if trainer.logger is not None:
        trainer.logger.log_metrics(metrics, step=trainer.global_step)
        trainer.logger.save()
    from cicfw.sweeps import write_job_metrics

    write_job_metrics(run_dir, metrics)
    return summary


def _quote(s: str) -> str:
    return "'" + s.replace("\\", "\\\\").replace("'", "\\'") + "'"


@hydra.main(version_base="1.3", config_path="pkg://cicfw.conf", config_name="evaluate")
@report_user_errors
def main(cfg: DictConfig) -> float:
    from hydra.core.hydra_config import HydraConfig

    return float(evaluate(cfg, Path(HydraConfig.get().runtime.output_dir))["success"])


if __name__ == "__main__":
    main()
