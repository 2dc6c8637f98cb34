"""``python -m cicfw.evaluate``: the paper's closed-loop single-turn suite for a checkpoint or a policy.

    python -m cicfw.evaluate checkpoint=outputs/<run>/checkpoints/<best>.ckpt
    python -m cicfw.evaluate policy=expert suite.towns=[town_b]
    python -m cicfw.evaluate -m checkpoint=a.ckpt,b.ckpt        # one joined table in the sweep folder

Writes the episode rows (JSON + CSV), the paper's table (Markdown + LaTeX), a map per town with the
driven paths and a bar chart into the run folder, and returns the overall success rate (%) so sweepers
can use it. ``evaluate_checkpoint`` runs the same from Python (``cicfw train evaluate_after=true``),
``evaluate_policy`` from plain specs. Finished episodes are kept as they finish: the same command with
the same output folder (``hydra.run.dir=<the killed run's folder>``) resumes a killed run.
"""
from __future__ import annotations

import errno
import hashlib
import json
import logging
import shlex
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, Sequence

import hydra
from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.errors import ConfigCompositionException
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from cicfw.benchmark import schema as evaluate_schema
from cicfw.benchmark.evaluation_report import (REPORT_FILES, REPORT_RECORD, find_runs, markdown_table, write_joined,
                                               write_run)
from cicfw.benchmark.finished_run import Run, save_trajectories
from cicfw.benchmark.journal import EpisodeLog
from cicfw.benchmark.plots import bar_chart, town_maps
from cicfw.benchmark.policy import POLICIES, Policy, make_policy
from cicfw.benchmark.runner import RunnerConfig, run, server_specs
from cicfw.benchmark.suite import build_suite, make_backend, town_label
from cicfw.benchmark.trained_sets import checkpoint_run_data, checkpoint_sets, earlier_data, training_set_overrides
from cicfw.benchmark.video import film_name_bytes, film_path, run_weather_family, select_episodes, write_video
from cicfw.core.config_checks import SchemaError, check_kwargs, checked, checked_seed
from cicfw.core.errors import USER_ERRORS, CicfwError, ConfigError, Interrupted, on_interrupt, report_user_errors
from cicfw.core.files import temp_name_bytes
from cicfw.core.override_hints import composition_error
from cicfw.core.run_folder import claim_folder, name_max, release_folder_locks, undo_run_folder
from cicfw.core.spawning import WorkerRefused, check_spawn_safe
from cicfw.core.sweeps import override_values, taking_turns, write_job_metrics
from cicfw.data.provenance import file_sha256
from cicfw.export.agent import torch_device
from cicfw.model.checkpoint import CheckpointBytes, resolve_checkpoint
from cicfw.sim.town import load_town
from cicfw.sim.render.weather import DEFAULT_FAMILY

log = logging.getLogger("cicfw.evaluate")

#: how often (seconds) a running evaluation rewrites its partial report as episodes finish: a killed run's
#: table then counts what had finished by then, not the none of its start; rarer, a long suite's rows are
#: not rewritten after every episode
PARTIAL_REPORT_EVERY_S = 10.0


def policy_spec(cfg: DictConfig) -> dict[str, Any]:
    """The policy's plain config (``name:`` + kwargs), with the row label from ``name=`` if given."""
    spec = OmegaConf.to_container(cfg.policy, resolve=True)
    assert isinstance(spec, dict)
    if cfg.get("checkpoint") and spec.get("name") != "checkpoint":
        raise CicfwError(f"checkpoint= is only read by policy=checkpoint, but policy={spec.get('name')}; "
                         f"drop checkpoint= or use policy=checkpoint", key="checkpoint", value=cfg.get("checkpoint"))
    if spec.get("name") == "checkpoint" and cfg.get("checkpoint") and spec.get("checkpoint") \
            and str(spec["checkpoint"]) != str(cfg.checkpoint):  # policy.checkpoint= replaced ${checkpoint}
        raise CicfwError(f"checkpoint={cfg.checkpoint} and policy.checkpoint={spec['checkpoint']} name two models; "
                         f"give checkpoint= alone", key="policy.checkpoint", value=spec["checkpoint"])
    if spec.get("name") == "checkpoint" and not spec.get("checkpoint"):
        raise CicfwError("no checkpoint to evaluate: give checkpoint=path/to.ckpt (written by cicfw train), "
                         "or policy=expert for the reference driver", key="checkpoint")
    if cfg.get("name"):
        spec["label"] = str(cfg.name)
    return spec


def evaluate(cfg: DictConfig, run_dir: Path, new_folder_hint: str | None = None,
             resume_hint: str | None = None, on_start: Callable[[], Any] | None = None, *,
             claim: bool = True) -> dict[str, Any]:
    """Run the suite described by ``cfg`` (conf/evaluate.yaml), write the report into ``run_dir``,
    return the summary (overall ``success`` % and per-column ``cells``). Resumes in ``run_dir``
    (see ``evaluate_policy``; ``new_folder_hint`` ends its error for a folder of another evaluation,
    ``resume_hint`` its ``Interrupted`` message, ``on_start`` is called once the folder is this run's).
    ``cfg`` is checked where it was composed: ``compose_config``, or the app's ``SchemaCheck`` callback.
    ``run_dir`` holding another app's run or files no cicfw app wrote (a ``table.md`` of your own), or inside
    another app's run (``<train run>/checkpoints``), is refused before anything is written, in one
    ``RunFolderError`` naming ``run_dir`` (``claim_folder``, as the app claims its folder); ``claim=False``:
    the caller claimed it (the app, a training run's ``evaluate/``, a reproduction's cell)."""
    if claim:
        claim_folder(run_dir, "evaluate", "run_dir")
    res = evaluate_policy(
        policy_spec(cfg), OmegaConf.to_container(cfg.suite, resolve=True),
        OmegaConf.to_container(cfg.runner, resolve=True), run_dir,
        sim=OmegaConf.to_container(cfg.sim, resolve=True), seed=cfg.seed,
        label=str(cfg.name) if cfg.name else None, progress_bar=cfg.progress_bar, maps=cfg.maps,
        video=list(cfg.video or []), video_max=cfg.video_max, new_folder_hint=new_folder_hint,
        resume_hint=resume_hint, on_start=on_start, claim=False)  # claimed above, or by the caller
    join_sweep()
    return res.summary


@dataclass
class EvalResult:
    """What ``evaluate_policy`` returns (the run folder holds the same, see docs/evaluation.md)."""

    summary: dict[str, Any]  # summary.json: success % overall (null before any episode) and per table column ("cells"), reasons, complete
    rows: list[dict[str, Any]]  # one per episode of the suite, in episode order (episodes.json's rows)
    run_dir: Path
    driven: int  # episodes driven by this call
    reused: int  # episodes kept from earlier, interrupted calls into the same run_dir

    @property
    def success(self) -> float | None:
        """Overall reach-destination success rate in percent; None when no episode has finished."""
        value = self.summary["success"]
        return None if value is None else float(value)


def evaluate_policy(policy: Mapping[str, Any], suite: Mapping[str, Any], runner: Mapping[str, Any] | None,
                    out_dir: str | Path, *, sim: Mapping[str, Any] | None = None, seed: int = 0,
                    label: str | None = None, progress_bar: bool = False, maps: bool = True,
                    video: Sequence[Any] = (), video_max: int = 8, new_folder_hint: str | None = None,
                    resume_hint: str | None = None, on_start: Callable[[], Any] | None = None,
                    claim: bool = True) -> EvalResult:
    """Drive the closed-loop suite with a policy into ``out_dir``, resuming what an earlier call left there
    (docs/evaluation.md, "Resuming": what is kept, which folder is refused, what may change between calls).

    ``policy`` is the policy's plain config (``{"name": "checkpoint", "checkpoint": "x.ckpt"}``,
    ``{"name": "expert"}``; conf/policy/), ``suite`` the ``suite:`` node of conf/evaluate.yaml
    (build_suite's arguments), ``runner`` the ``runner:`` node (RunnerConfig's fields, None for the
    defaults), ``sim`` the simulator spec (None: the embedded one). ``label`` names the table row (default:
    the policy's label). Config errors raise before anything is written; the report says ``"complete": true``
    only once every episode is driven and the trajectories and pictures are written; ``on_start`` is called once
    ``out_dir`` holds this evaluation's episode log; Ctrl-C raises ``Interrupted``, ending with
    ``resume_hint``. ``out_dir`` holding another app's run or files no cicfw app wrote is refused
    (``claim_folder``; ``claim=False``: the caller claimed it). Returns an ``EvalResult``.
    """
    out_dir = Path(out_dir)
    check_out_dir(out_dir)
    if claim:
        claim_folder(out_dir, "evaluate", "out_dir")
    spec = dict(policy)
    sim = dict(sim) if sim is not None else {"name": "embedded"}
    runner = dict(runner or {})
    suite = dict(suite)
    filmed = list(video)
    runner_cfg, episodes = plan_evaluation(spec, suite, runner, sim, seed, progress_bar, filmed, video_max)
    check_town_file_names(out_dir, episodes, maps, bool(filmed))
    pol: Policy | dict = make_policy(spec)  # a bad checkpoint fails here, before any driving
    # spawned workers import the calling script again: an unguarded one is refused now, before the folder's
    # lock, on which a worker running the script's evaluation over would wait
    if runner_cfg.resolve_workers(episodes, bool(pol.cameras)) > 1:
        check_spawn_safe("evaluate_policy", "runner.workers", runner_cfg.workers)
    label = label or spec.get("label") or pol.label
    # a checkpoint policy read its file once: the fingerprint hashes those bytes and each worker builds from them,
    # so a file replaced meanwhile (a training run's last.ckpt) cannot drive weights other than the recorded ones
    read = pol.source if isinstance(getattr(pol, "source", None), CheckpointBytes) else None
    built = {**spec, "checkpoint": read} if read is not None else spec
    fp, info = run_fingerprint(spec, suite, sim, runner_cfg, episodes, read)
    with EpisodeLog.open(out_dir, fp, info, hint=new_folder_hint or
                         f"give another output folder, or delete {str(out_dir)!r} to start over") as elog:
        if on_start is not None:
            on_start()
        missing = [e for e in episodes if e.index not in elog.rows]
        # the checkpoint as typed (relative to where it was run), and the file it named, absolute: a report
        # read from another directory, or moved, still names it
        meta = {"policy": spec["name"], "checkpoint": spec.get("checkpoint"), "seed": int(seed), "suite": suite,
                "runner": runner, "sim": sim, "fingerprint": fp,
                **({"checkpoint_file": info["checkpoint"]} if "checkpoint" in info else {})}
        log.info("evaluating %s on %d episodes (%s x %s)%s", label, len(episodes), ", ".join(map(str, suite["towns"])),
                 ", ".join(suite["weathers"]), f"; {elog.reused} kept from an earlier run, {len(missing)} to drive"
                 if elog.reused else "")
        if missing and runner_cfg.resolve_workers(missing, bool(pol.cameras)) > 1:
            del pol  # each worker process builds its own from the spec, with the bytes hashed here
            pol = built
        wall = 0.0
        if missing:
            write_run(out_dir, _report(out_dir, label, elog.rows, episodes, meta))  # marked partial: not final
            try:
                res = run(missing, pol, sim, runner_cfg, label=label,
                          on_episode=refreshing_report(elog, out_dir, lambda: _report(out_dir, label, elog.rows,
                                                                                      episodes, meta)))
                wall = res.wall_s
            except BaseException as stop:
                try:
                    write_run(out_dir, _report(out_dir, label, elog.rows, episodes, meta))
                except Exception as err:  # e.g. a full disk: the log still holds every finished episode
                    log.error("could not write the partial report: %s", err)
                kept = f"{len(elog.rows)} of {len(episodes)} episodes finished, kept in {out_dir}"
                again = resume_hint or 'call again with the same output folder to drive the rest'
                if isinstance(stop, KeyboardInterrupt):
                    raise Interrupted(f"{kept}: {again}") from None
                if isinstance(stop, OSError) and stop.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
                    raise OutputWriteError(f"could not write the episode log ({stop.strerror}); {kept}: free some "
                                           f"space, then {again}") from None
                if not isinstance(stop, WorkerRefused):  # the same command would stop the same way
                    log.error("stopped with %s; run the same command with the same output folder to drive the rest",
                              kept)
                raise
        meta.update(wall_s=round(wall, 2), episodes_driven=len(missing), episodes_reused=elog.reused)
        # the report that says "complete" is written last: a run stopped while its trajectories or pictures
        # are written keeps the partial report, and the same command writes them (driving nothing)
        unwritten = (f"all {len(episodes)} episodes finished, kept in {out_dir}, but the report and pictures are "
                     f"not all written: {resume_hint or 'call again with the same output folder'} (nothing is "
                     f"left to drive: it writes them)")
        with writing_outputs(out_dir), on_interrupt(unwritten):
            report = _report(out_dir, label, elog.rows, episodes, meta, final=True)
            save_trajectories(out_dir / "trajectories.npz", report.rows, elog.trajectories)
            pictures(report, elog.trajectories, out_dir, [str(t) for t in suite["towns"]], str(sim.get("name")),
                     int(seed), maps, select_episodes(report.rows, filmed, int(video_max)), run_weather_family(meta))
            summary = write_run(out_dir, report)
    steps = int(summary.get("steps", 0))
    rate = f", {steps / wall:.0f} frames/s" if missing and len(missing) == len(report.rows) and wall > 0 else ""
    log.info("%d episodes (%d driven now, %.1f s), %d steps%s\n%s", len(report.rows), len(missing), wall,
             steps, rate, markdown_table([report]))
    log.info("success %s; report in %s", percent(summary["success"]), out_dir)
    return EvalResult(summary=summary, rows=report.rows, run_dir=out_dir, driven=len(missing), reused=elog.reused)


def check_out_dir(out_dir: Path) -> None:
    """``out_dir`` is a folder or does not exist yet: a file there, or on the way to it, is one line naming
    ``out_dir`` and that file, before anything is loaded or driven (the episode log's folder was a bare
    ``FileExistsError``)."""
    for p in (out_dir, *out_dir.parents):
        if p.exists() or p.is_symlink():
            if not p.is_dir():
                where = "is a file" if p == out_dir else f"lies under the file {p}"
                raise CicfwError(f"out_dir={out_dir} {where}, not a folder; give a folder that is missing, empty or "
                                 f"this evaluation's", key="out_dir", value=str(out_dir))
            return


def check_town_file_names(out_dir: Path, episodes: Sequence[Any], maps: bool, videos: bool) -> None:
    """The files named after a town (its map, its episodes' videos), under their temporary names while written
    (cicfw.core.files), fit the filesystem: a town file's long stem is one line now, not after the driving."""
    sizes = [(town_label(e.town), temp_name_bytes(f"map_{town_label(e.town)}.png")) for e in episodes if maps]
    sizes += [(town_label(e.town), film_name_bytes(e.key)) for e in episodes if videos]
    limit = name_max(out_dir)
    for town, size in sizes:
        if size > limit:
            raise ConfigError("suite.towns", town, "a town whose file names fit", f"suite.towns: the town {town!r} "
                              f"makes file names of {size} bytes (its map, its videos), more than "
                              f"this filesystem allows ({limit}); give the town file a shorter name")


def percent(value: float | None) -> str:
    """A success rate as the log says it: ``72.50%``, or ``none (no episodes)`` for summary.json's null."""
    return "none (no episodes)" if value is None else f"{float(value):.2f}%"


class OutputWriteError(CicfwError):
    """The report or a picture could not be written (a full disk ...); the driven episodes are kept."""


@contextmanager
def writing_outputs(out_dir: Path) -> Iterator[None]:
    """An ``OSError`` while the report, trajectories and pictures are written becomes one
    ``OutputWriteError`` line: which file, why, and that the episodes are kept (each file is written
    whole or not at all, ``cicfw.core.files``); the same command writes them again without driving."""
    try:
        yield
    except OSError as err:
        where = err.filename or out_dir
        why = "no space left on the device" if err.errno in (errno.ENOSPC, errno.EDQUOT) else (err.strerror or str(err))
        raise OutputWriteError(f"could not write {str(where)!r} ({why}); every episode is driven and kept in "
                               f"{str(out_dir)!r}: free some space, then run the same command with the same output "
                               f"folder, which drives nothing again and writes the report and pictures") from None


def plan_evaluation(spec: Mapping[str, Any], suite: Mapping[str, Any], runner: Mapping[str, Any],
                    sim: Mapping[str, Any], seed: int = 0, progress_bar: bool = False, video: Sequence[Any] = (),
                    video_max: int = 8) -> tuple[Any, list[Any]]:
    """Everything about an evaluation that can be checked without its policy's weights, checked: the
    runner's settings, the workers against the simulator, the policy's keys, the suite (towns,
    weathers, ``limit``) and the episodes ``video`` names. Returns the RunnerConfig and the episodes;
    raises one ``ValueError`` line before anything is driven or written."""
    checked_seed(seed)  # as train's: seed=-1 was taken
    checked(evaluate_schema.RUNNER, runner, "runner")
    checked(evaluate_schema.SUITE, suite, "suite")  # a Python caller's typo (limt=1): named, not a TypeError
    runner_cfg = RunnerConfig(**{**runner, "seed": int(seed), "progress_bar": bool(progress_bar)})
    server_specs(sim, runner_cfg.workers)  # runner.workers that do not fit the simulator fail here
    kwargs = {k: v for k, v in spec.items() if k != "name"}
    check_kwargs("policy", f"policy {spec.get('name')!r}", POLICIES.get(str(spec.get("name"))), kwargs,
                 extra_keys=("name",))
    check_policy_device(kwargs.get("device"))
    episodes = build_suite(make_backend(sim), **suite)  # unknown towns and weathers, suite.limit=0 fail here
    if isinstance(video_max, bool) or not isinstance(video_max, int) or video_max < 0:  # -1 would film nothing
        raise ConfigError("video_max", video_max, "a whole number >= 0 (0: no videos)")
    select_episodes([{"episode": e.index, "key": e.key, "success": False} for e in episodes], video, video_max)
    return runner_cfg, episodes


def check_config(cfg: DictConfig) -> None:
    """Every value ``evaluate`` checks before it loads a policy's weights or drives (``plan_evaluation``), for
    a composed config: a multirun checks each job's config with it before its first job drives
    (``cicfw.core.override_hints.SweepJobsCheck``, conf/evaluate.yaml)."""
    plain = {k: OmegaConf.to_container(cfg[k], resolve=True) for k in ("suite", "runner", "sim")}
    plan_evaluation(policy_spec(cfg), plain["suite"], plain["runner"], plain["sim"], seed=cfg.seed,
                    video=list(cfg.video or []), video_max=cfg.video_max)


def check_policy_device(device: Any) -> None:
    """``policy.device`` a torch device this machine has (``cuda`` on a CPU build failed when the policy
    was built: after the training, for ``cicfw train evaluate_after=true``)."""
    if device is None:
        return

    try:
        torch_device(str(device))
    except ValueError as err:
        raise CicfwError(str(err).replace("device=", "policy.device=", 1), key="policy.device", value=device) from None


_DRIVES_THIS_RUN = ("it drives this run's best checkpoint and logs its success as this run's closed_loop/success; "
                    "evaluate another checkpoint with python -m cicfw.evaluate checkpoint=...")
#: what the evaluation after training does not take from ``evaluate_overrides``, and why
NOT_AFTER_TRAINING = {
    "checkpoint": _DRIVES_THIS_RUN,
    "policy.checkpoint": _DRIVES_THIS_RUN,
    "policy": "it drives this run's checkpoint (policy=checkpoint); evaluate another policy with "
              "python -m cicfw.evaluate policy=...",
    "hydra": "it writes into the run folder's evaluate/ and takes no hydra options",
}


def _override_keys(overrides: Any) -> list[tuple[str, str]]:
    """``evaluate_overrides`` as (override, its key or config group) pairs: a list of override strings that
    Hydra parses, or one ``ValueError`` line saying which is not."""
    if OmegaConf.is_list(overrides):
        overrides = OmegaConf.to_container(overrides, resolve=True)
    if overrides is None:
        overrides = []
    if not isinstance(overrides, (list, tuple)) or not all(isinstance(o, str) for o in overrides):
        raise CicfwError(f"must be a list of override strings such as [\"suite.towns=[town_a]\"], got {overrides!r}")
    parser, out = OverridesParser.create(), []
    for o in overrides:
        try:
            out.append((o, parser.parse_override(o).key_or_group))
        except Exception as err:
            raise CicfwError(f"cannot parse {o!r}: {str(err).strip().splitlines()[0]}") from None
    return out


def check_evaluation_overrides(overrides: Any) -> None:
    """``cicfw train evaluate_after=true``: the evaluation's config (conf/evaluate.yaml with
    ``evaluate_overrides``) composed and checked now, before the first batch, rather than after the
    training (``plan_evaluation`` with the checkpoint still to be written); an override that would make it
    drive something else than this run's checkpoint (``checkpoint=``, ``policy=expert``, ``hydra.*``) is
    refused. One ``ValueError`` line starting ``evaluate_overrides:`` (a ``SchemaError``, its kind and key
    kept, for what the schema refuses)."""
    try:
        pairs = _override_keys(overrides)
        for o, key in pairs:
            root = "hydra" if key.split(".")[0].split("/")[0] == "hydra" else key
            if root in NOT_AFTER_TRAINING and not (root == "policy" and o.split("=", 1)[-1].strip() == "checkpoint"):
                raise CicfwError(f"{o} cannot be given: {NOT_AFTER_TRAINING[root]}")
        cfg = compose_config([f"checkpoint={_quote('<the trained checkpoint>')}", *(o for o, _ in pairs)])
        plan_evaluation(policy_spec(cfg), OmegaConf.to_container(cfg.suite, resolve=True),
                        OmegaConf.to_container(cfg.runner, resolve=True), OmegaConf.to_container(cfg.sim, resolve=True),
                        cfg.seed, False, list(cfg.video or []), cfg.video_max)
    except SchemaError as err:
        raise SchemaError(f"evaluate_overrides: {err}", err.key, err.kind) from None
    except (ValueError, FileNotFoundError) as err:
        text = err.args[0] if isinstance(err, (KeyError, FileNotFoundError)) and err.args else err
        raise CicfwError(f"evaluate_overrides: {text}", key="evaluate_overrides", value=overrides) from None


#: policy keys that change how fast or where a policy runs, never which episodes it drives
_POLICY_RUNTIME_KEYS = ("label", "device", "threads")
#: simulator keys that say how to reach a server, not what it simulates
_SIM_RUNTIME_KEYS = ("host", "port", "ports")


def run_fingerprint(spec: Mapping[str, Any], suite: Mapping[str, Any], sim: Mapping[str, Any], runner: Any,
                    episodes: Sequence[Any], read: CheckpointBytes | None = None
                    ) -> tuple[dict[str, Any], dict[str, Any]]:
    """What decides a run's episodes (a folder resumes only with the same), and readable extras.

    The checkpoint counts by its contents (sha256: of ``read``, the bytes the policy was built from, when
    given), not its path, and so does a town given as a file; the runner by its episode rules (off-road
    limits, target speed) and seed, not its batch size or worker count."""
    pol = {k: v for k, v in spec.items() if k not in _POLICY_RUNTIME_KEYS}
    info: dict[str, Any] = {}
    if pol.get("checkpoint"):
        given = pol.pop("checkpoint")
        path = read.path if read is not None else resolve_checkpoint(given)
        pol["checkpoint_sha256"] = read.sha256 if read is not None else file_sha256(path)
        info["checkpoint"] = str(path)
    episode_list = [[e.key, e.route, e.command, e.town_set, e.weather_set] for e in episodes]
    fp = {
        "policy": pol,
        "suite": dict(suite),
        "episodes": hashlib.sha256(json.dumps(episode_list).encode()).hexdigest()[:16],
        "seed": int(runner.seed),
        "sim": {k: v for k, v in sim.items() if k not in _SIM_RUNTIME_KEYS and not str(k).endswith("timeout_s")},
        "runner": {"off_road_s": runner.off_road_s, "off_road_level": runner.off_road_level,
                   "target_speed_kmh": runner.target_speed_kmh},
    }
    # a town given as a file counts by its contents too: its routes keep their names when the file is edited
    town_files = sorted({str(e.town) for e in episodes if str(e.town).endswith((".yaml", ".yml"))})
    if town_files:
        fp["town_files"] = {t: hashlib.sha256(Path(t).expanduser().read_bytes()).hexdigest()[:16] for t in town_files}
    return fp, info


def refreshing_report(elog: EpisodeLog, out_dir: Path, partial: Callable[[], Run]) -> Callable[[dict, dict], None]:
    """``elog.add``, and the ``partial()`` report rewritten when ``PARTIAL_REPORT_EVERY_S`` have passed since
    the last: the run folder's own table of a killed run counts the episodes finished by then. A report that
    cannot be written is logged and driving goes on (the log keeps every episode)."""
    last = time.monotonic()

    def on_episode(row: dict, traj: dict) -> None:
        nonlocal last
        elog.add(row, traj)
        if time.monotonic() - last >= PARTIAL_REPORT_EVERY_S:
            try:
                write_run(out_dir, partial())
            except OSError as err:
                log.warning("could not rewrite the partial report: %s", err)
            last = time.monotonic()

    return on_episode


def _report(out_dir: Path, label: str, rows_by_index: Mapping[int, dict], episodes: Sequence[Any],
            meta: dict[str, Any], final: bool = False) -> Run:
    """The report of the episodes finished so far (not written), marked complete only when every one is and
    it is the ``final`` report, written after the trajectories and pictures: a run stopped before that (even
    after its last episode) must not look finished while they are missing."""
    rows = [rows_by_index[e.index] for e in episodes if e.index in rows_by_index]
    complete = final and len(rows) == len(episodes)
    meta = {**meta, "complete": complete, "episodes_total": len(episodes),
            "steps": sum(int(r["steps"]) for r in rows)}
    return Run(label=label, rows=rows, meta=meta, path=out_dir)


def pictures(report, trajectories: dict, run_dir: Path, towns: Sequence[str], sim_name: str, seed: int,
             maps: bool, filmed: Sequence[dict], family: str = DEFAULT_FAMILY) -> None:
    """The map per town, the bar chart, and the requested videos."""
    towns = {town_label(t): str(t) for t in towns}
    if maps:
        town_maps(report, trajectories, run_dir, towns)
    bar_chart([report], run_dir / "success_bars.png")
    if filmed:
        if sim_name != "embedded":
            log.warning("videos are re-rendered with the embedded simulator; sim=%s has none", sim_name)
            return
        for r in filmed:
            path = film_path(run_dir, r["key"])
            write_video(path, r, trajectories[r["key"]], load_town(towns[r["town"]]), r["weather"], seed, family=family)
            log.info("video: %s", path)


def unjoined_sweep(sweep_dir: Path) -> list[str]:
    """A sweep whose runs one table cannot hold keeps no sweep table: the one an earlier job joined (job 0's
    alone, say) would name one job of several. Removes those files unless a ``cicfw report`` wrote them there
    (its ``report.json``); returns the names removed."""
    if (sweep_dir / REPORT_RECORD).exists():
        return []
    removed = [name for name in REPORT_FILES if (sweep_dir / name).is_file()]
    for name in removed:
        (sweep_dir / name).unlink(missing_ok=True)
    return removed


def join_sweep() -> None:
    """In a multirun, join every finished run of the sweep into one table in the sweep folder."""
    try:
        if not HydraConfig.initialized() or HydraConfig.get().mode != RunMode.MULTIRUN:
            return
        if HydraConfig.get().job.config_name != "evaluate":  # e.g. reproduce's cells: that app reports itself
            return
        sweep_dir = Path(HydraConfig.get().sweep.dir)
    except Exception:
        return

    # jobs of a parallel launcher finishing at once take turns: a join read while another job was still
    # driving (its row PARTIAL) must not be written over that job's later, complete join
    with taking_turns(sweep_dir):
        try:
            runs = find_runs([sweep_dir], partial="include")  # a job stopped part-way shows as PARTIAL
        except CicfwError as err:  # e.g. a sweep over suite=single_turn,junctions: one table cannot hold them
            removed = unjoined_sweep(sweep_dir)
            tables = sorted(str(p.relative_to(sweep_dir)) for p in sweep_dir.glob("*/table.md"))
            log.warning("the sweep's runs are not joined into one table: %s; each job's table is in its own "
                        "folder (%s)%s", err, ", ".join(f"{sweep_dir}/{t}" for t in tables),
                        f"; removed the sweep folder's earlier join ({', '.join(removed)})" if removed else "")
            return
        write_joined(runs, sweep_dir)
    log.info("joined %d run(s) of the sweep into %s", len(runs), sweep_dir / "table.md")


def compose_config(overrides: Sequence[str] = ()) -> DictConfig:
    """conf/evaluate.yaml with ``overrides``, from inside or outside a running Hydra app, and what composing
    lets through checked (``cicfw.benchmark.schema.check``: +vide=[0] would silently film nothing). What is
    refused is one line: a ``SchemaError`` naming the key for what the schema refuses, else a ``ValueError``."""
    try:
        if GlobalHydra.instance().is_initialized():
            cfg = compose("evaluate", overrides=list(overrides))
        else:
            with initialize_config_module("cicfw.conf", version_base="1.3"):
                cfg = compose("evaluate", overrides=list(overrides))
    except ConfigCompositionException as err:
        raise composition_error(err, list(overrides)) from None
    evaluate_schema.check(cfg)
    return cfg


def evaluate_checkpoint(checkpoint: str | Path, run_dir: str | Path, overrides: Sequence[str] = (),
                        resume_hint: str | None = None, *, claim: bool = True) -> dict[str, Any]:
    """The suite for one checkpoint, configured by conf/evaluate.yaml plus ``overrides``; ``run_dir`` is
    claimed as ``evaluate`` claims it (``claim=False``: the caller holds it)."""
    cfg = compose_config([f"checkpoint={_quote(str(checkpoint))}", *overrides])
    return evaluate(cfg, Path(run_dir), resume_hint=resume_hint, claim=claim)


#: what ``evaluate_after=true`` drives after a ``trainer.fast_dev_run`` (one batch: a check that the
#: config runs, not a model worth the whole suite): the first pair of each town, under every weather
FAST_DEV_RUN_SUITE = "suite.limit=1"
#: evaluate_overrides keys that choose the suite's size: given one, a fast_dev_run drives what it says
_SUITE_SIZE_KEYS = ("suite.limit", "suite.pairs")


def after_training_overrides(overrides: Sequence[str], fast_dev_run: Any) -> tuple[list[str], str]:
    """``evaluate_overrides`` as the evaluation after training applies them, and what that drives in words:
    after ``trainer.fast_dev_run`` a short suite (``FAST_DEV_RUN_SUITE``) unless the overrides size it."""
    overrides = [str(o) for o in overrides]
    if not fast_dev_run:
        return overrides, "the suite of conf/evaluate.yaml with evaluate_overrides"
    if {key for _, key in _override_keys(overrides)} & set(_SUITE_SIZE_KEYS):
        return overrides, "the suite as evaluate_overrides size it"
    return [*overrides, FAST_DEV_RUN_SUITE], (f"a short suite after trainer.fast_dev_run ({FAST_DEV_RUN_SUITE}: the "
                                              f"first pair of each town; evaluate_overrides=[suite.limit=null] drives "
                                              f"the whole suite)")


def saved_checkpoint(trainer: Any) -> str:
    """The checkpoint ``evaluate_after_training`` drives, "" where no callback saved one. The best checkpoint's
    callback comes first; without validation it saved none, and last.ckpt's has the final weights: saving them
    again as final.ckpt would keep two copies of the same weights."""
    return next((p for cb in trainer.checkpoint_callbacks for p in (cb.best_model_path, cb.last_model_path)
                 if p and Path(p).is_file()), "")


def trained_on(earlier: int) -> str:
    """Words for the table's training columns of a run resumed on other data (``earlier`` data sets before)."""
    return (f" (the union over all {earlier + 1} data sets it trained on: it resumed on other data, and its "
            f"data.json keeps the earlier ones under 'before')" if earlier else "")


def evaluate_after_training(cfg: DictConfig, trainer: Any, run_dir: Path) -> dict[str, Any]:
    """``cicfw train evaluate_after=true``: the suite on the run's best checkpoint (else its last one,
    else the final weights saved now as ``checkpoints/final.ckpt``: a ``trainer.fast_dev_run`` saves
    none), into ``<run_dir>/evaluate``; after a ``trainer.fast_dev_run``, a short suite
    (``after_training_overrides``). Logs what it saved and drives, then ``closed_loop/success`` and one
    ``closed_loop/success/<cell>`` per table column to the trainer's logger and to the job's
    ``metrics.json`` (the sweep summary's ``closed_loop_success`` column); returns the summary, whose
    ``success`` is a number: it returns only once every episode is driven (a stop raises ``Interrupted``)."""
    run_dir = Path(run_dir)
    path = saved_checkpoint(trainer)
    if not path:
        path = str(run_dir / "checkpoints" / "final.ckpt")
        trainer.save_checkpoint(path)
        why = "trainer.fast_dev_run saves none" if trainer.fast_dev_run else "none was saved"
        log.info("training wrote no checkpoint (%s): wrote its final weights to %s for the closed-loop evaluation",
                 why, path)
    overrides, what = after_training_overrides(cfg.get("evaluate_overrides") or [], trainer.fast_dev_run)
    # the table's training columns: the sets the checkpoint recorded when training started, as cicfw evaluate reads them
    earlier = earlier_data(Path(path))
    trained_in = training_set_overrides(cfg.get("data"), overrides, checkpoint_sets(Path(path)), path, earlier)
    if trained_in:
        log.info("the table's training columns are the data's towns and weathers%s: %s", trained_on(earlier),
                 " ".join(trained_in))
        overrides = [*overrides, *trained_in]
    out = run_dir / "evaluate"
    log.info("closed-loop evaluation of %s: %s, into %s", path, what, out)
    command = shlex.join(["python", "-m", "cicfw.evaluate", f"checkpoint={path}", *overrides, f"hydra.run.dir={out}"])
    summary = evaluate_checkpoint(path, out, overrides, resume_hint=f"training finished (checkpoints in "
                                  f"{Path(path).parent}); drive the rest with {command}",
                                  claim=False)  # inside the training run's folder, which it holds
    metrics = {**({"closed_loop/success": summary["success"]} if summary["success"] is not None else {}),
               **{f"closed_loop/success/{k}": v["rate"] for k, v in summary["cells"].items()}}
    if trainer.logger is not None and metrics:
        trainer.logger.log_metrics(metrics, step=trainer.global_step)
        trainer.logger.save()

    write_job_metrics(run_dir, metrics)
    return summary


def _quote(s: str) -> str:
    return "'" + s.replace("\\", "\\\\").replace("'", "\\'") + "'"


def with_trained_sets(cfg: DictConfig, overrides: Sequence[str]) -> None:
    """``policy=checkpoint``: the table's training columns set in ``cfg`` to the towns and weathers the
    checkpoint's run collected its data in (``training_set_overrides``, as the evaluation after training
    does: those it recorded when training started, else its data's metadata now), each unless ``overrides``
    give it; nothing for a checkpoint outside a run folder, or data that does not say. A checkpoint that cannot
    be read is left to the evaluation's own refusal."""
    spec = OmegaConf.to_container(cfg.policy, resolve=True)
    path = cfg.get("checkpoint") or spec.get("checkpoint")
    if spec.get("name") != "checkpoint" or not path:
        return
    try:
        ckpt = resolve_checkpoint(path)
        data, recorded, earlier = checkpoint_run_data(ckpt), checkpoint_sets(ckpt), earlier_data(ckpt)
    except Exception:  # a bad checkpoint: evaluate names it
        return
    trained_in = training_set_overrides(data, overrides, recorded, whose=f"checkpoint {ckpt}", earlier=earlier)
    if trained_in:
        log.info("the table's training columns are the towns and weathers the checkpoint's data was collected "
                 "in%s%s: %s", " (as it recorded them)" if recorded is not None else "", trained_on(earlier),
                 " ".join(trained_in))
        for key, value in override_values(trained_in).items():
            OmegaConf.update(cfg, key, value)


@hydra.main(version_base="1.3", config_path="pkg://cicfw.conf", config_name="evaluate")
@report_user_errors
def main(cfg: DictConfig) -> float:
    out = Path(HydraConfig.get().runtime.output_dir)
    key = "hydra.sweep.dir" if HydraConfig.get().mode == RunMode.MULTIRUN else "hydra.run.dir"
    hint = f"give a new output folder ({key}=<new folder>) or delete {str(out)!r} to start over"
    resume = f"run the same command with {key}={out if key == 'hydra.run.dir' else out.parent} to drive the rest"
    started = []
    try:
        with_trained_sets(cfg, list(HydraConfig.get().overrides.task))
        success = evaluate(cfg, out, new_folder_hint=hint, resume_hint=resume, on_start=lambda: started.append(True),
                           claim=False)["success"]  # claimed and locked by EvaluateRunFolderCheck
    except USER_ERRORS:  # refused before the folder was this run's (a bad checkpoint, another evaluation's
        if not started and key == "hydra.run.dir":  # episodes): the folder as it was, .hydra and log included
            undo_run_folder(out)  # under the folder's lock, which EvaluateRunFolderCheck took
        raise
    finally:
        release_folder_locks(out)  # (the episode log lets go of it itself once it has taken it)
    return float("nan") if success is None else float(success)  # null: no episode (a finished suite has some)

