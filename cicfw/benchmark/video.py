"""Short MP4 videos of chosen episodes: the centre camera as the policy saw it, with the command,
the steering and the speed overlaid. Frames are re-rendered from the recorded poses (the renderer is
deterministic for a seed and time), so any episode of a finished run can be filmed afterwards."""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any, Mapping, Sequence

import cv2
import numpy as np

from cicfw.benchmark.finished_run import load_run, load_trajectories
from cicfw.benchmark.suite import town_label
from cicfw.core.errors import CicfwError, install_app_handlers
from cicfw.core.run_folder import name_max
from cicfw.sim.env import get_renderer
from cicfw.sim.render.weather import DEFAULT_FAMILY, LEGACY_FAMILY, get_weather
from cicfw.sim.town import load_town


COMMAND_TEXT = {2: ("FOLLOW", (200, 200, 200)), 3: ("LEFT", (80, 170, 255)), 4: ("RIGHT", (255, 110, 90)),
                5: ("STRAIGHT", (120, 230, 120))}
SCALE = 3  # 200x88 -> 600x264
PANEL = 84  # px of text panel under the image


def select_episodes(rows: Sequence[Mapping[str, Any]], wanted: Sequence[Any], limit: int) -> list[Mapping]:
    """The rows named by ``wanted`` (episode indices, keys ``town/weather/pair``, or ``"failures"``);
    an unknown one raises an error listing a few valid keys."""
    by_index = {int(r["episode"]): r for r in rows}
    by_key = {str(r["key"]): r for r in rows}
    out: list[Mapping] = []
    for w in wanted:
        if isinstance(w, str) and w in ("failures", "failed"):
            out += [r for r in rows if not r["success"]]
        elif isinstance(w, str) and w in ("successes", "all"):
            out += [r for r in rows if r["success"] or w == "all"]
        elif isinstance(w, int) or (isinstance(w, str) and w.isdigit()):
            if int(w) not in by_index:
                raise CicfwError(f"video: no episode {w} in this run (episodes 0..{len(rows) - 1})", value=w)
            out.append(by_index[int(w)])
        elif str(w) in by_key:
            out.append(by_key[str(w)])
        else:
            some = ", ".join(list(by_key)[:3])
            raise CicfwError(f"video: unknown episode {w!r}; give episode indices, keys such as {some}, "
                             f"or 'failures'", value=w)
    return list({r["key"]: r for r in out}.values())[: max(int(limit), 0)]  # each once, first-named first


def _overlay(img: np.ndarray, step: int, tr: Mapping[str, np.ndarray], title: str) -> np.ndarray:
    """The upscaled frame (BGR) above a panel: the episode, the command, a steering bar, speed, time."""
    h, w = img.shape[0] * SCALE, img.shape[1] * SCALE
    canvas = np.zeros((h + PANEL, w, 3), np.uint8)
    canvas[:h] = cv2.resize(cv2.cvtColor(img, cv2.COLOR_RGB2BGR), (w, h), interpolation=cv2.INTER_NEAREST)
    font = cv2.FONT_HERSHEY_SIMPLEX
    cv2.putText(canvas, title, (10, h + 18), font, 0.45, (200, 200, 200), 1, cv2.LINE_AA)
    cmd = int(tr["command"][step])
    text, rgb = COMMAND_TEXT.get(cmd, (str(cmd), (255, 255, 255)))
    y0 = h + 48
    cv2.putText(canvas, text, (10, y0), font, 0.75, rgb[::-1], 2, cv2.LINE_AA)
    steer = float(tr["steer"][step])
    # steering bar: centre tick, bar from the centre towards the steering side (left = negative)
    bx0, bx1, by = 170, w - 20, y0 - 9
    cx = (bx0 + bx1) // 2
    cv2.rectangle(canvas, (bx0, by - 8), (bx1, by + 8), (90, 90, 90), 1)
    cv2.line(canvas, (cx, by - 11), (cx, by + 11), (200, 200, 200), 1)
    tip = int(cx + steer * (bx1 - bx0) / 2)
    cv2.rectangle(canvas, (min(cx, tip), by - 7), (max(cx, tip), by + 7), (0, 200, 255), -1)
    cv2.putText(canvas, "L", (bx0 - 16, by + 5), font, 0.45, (160, 160, 160), 1, cv2.LINE_AA)
    cv2.putText(canvas, "R", (bx1 + 5, by + 5), font, 0.45, (160, 160, 160), 1, cv2.LINE_AA)
    info = f"steer {steer:+.2f}    speed {float(tr['speed_kmh'][step]):4.1f} km/h    t {step / 10:4.1f} s"
    cv2.putText(canvas, info, (10, h + PANEL - 10), font, 0.5, (230, 230, 230), 1, cv2.LINE_AA)
    return canvas


def run_weather_family(meta: Mapping[str, Any]) -> str:
    """The weather family a run drove under (its ``sim.weather_family``); a run recorded before the
    families drove under the legacy one."""
    return str((meta.get("sim") or {}).get("weather_family", LEGACY_FAMILY))


def film_path(run_dir: Path, key: str) -> Path:
    """Where episode ``key``'s film goes: ``<run>/videos/<key with / as _>.mp4``."""
    return Path(run_dir) / "videos" / f"{key.replace('/', '_')}.mp4"


def _filming(path: Path) -> Path:
    """The temporary name a film is written to, renamed to ``path`` once whole."""
    return path.with_name(f".{path.stem}.tmp.mp4")


def film_name_bytes(key: str) -> int:
    """How long (bytes) episode ``key``'s longest film file name is (its temporary one): what the filesystem's
    name limit must take, checked before anything is rendered."""
    return len(os.fsencode(_filming(film_path(Path("."), key)).name))


def write_video(path: Path, row: Mapping[str, Any], tr: Mapping[str, np.ndarray], town: Any, weather: str,
                seed: int = 0, fps: float = 10.0, family: str = DEFAULT_FAMILY) -> Path:
    """Film one episode to ``path`` (MP4, written to a temporary name first), its ``weather`` rendered as
    ``family`` renders it: the film shows what the run's cameras saw."""
    renderer = get_renderer(town, get_weather(weather, family), seed, ("centre",))
    outcome = "reached the goal" if row["success"] else f"failed: {row['reason'].replace('_', ' ')}"
    title = f"{row['key']}  ({row['route']}):  {outcome}"
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _filming(path)
    writer, filmed = None, False
    try:
        for k in range(len(tr["x"])):
            img = renderer.render(float(tr["x"][k]), float(tr["y"][k]), float(tr["yaw"][k]), k * 0.1)["centre"]
            frame = _overlay(img, k, tr, title)
            if writer is None:
                writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), fps,
                                         (frame.shape[1], frame.shape[0]))
                if not writer.isOpened():
                    raise RuntimeError("OpenCV could not open an MP4 writer (codec mp4v)")
            writer.write(frame)
        filmed = True
    finally:
        if writer is not None:
            writer.release()
        if not filmed:  # a film cut short (an error, Ctrl-C) is no film: no half-written file left
            tmp.unlink(missing_ok=True)
    os.replace(tmp, path)
    return path


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m cicfw.benchmark.video RUN_DIR [EPISODE ...]``: film episodes of a finished run."""
    ap = argparse.ArgumentParser(prog="python -m cicfw.benchmark.video",
                                 description="Film episodes of a finished evaluation run (MP4, centre camera).")
    ap.add_argument("run_dir", help="an evaluation run folder (episodes.json, trajectories.npz)")
    ap.add_argument("episodes", nargs="*", default=["failures"],
                    help="episode numbers, keys (town/weather/pair) or 'failures' (default)")
    ap.add_argument("--max", type=int, default=8, help="at most this many videos")
    args = ap.parse_args(argv)
    if args.max < 1:  # it would cut every chosen episode and then report that nothing was selected
        print(f"cicfw: error: --max={args.max} is not valid; accepted: an integer >= 1 (videos at most)", file=sys.stderr)
        return 2
    try:
        run = load_run(args.run_dir)
        chosen = select_episodes(run.rows, [int(e) if e.isdigit() else e for e in args.episodes], args.max)
        trajs = load_trajectories(args.run_dir)
    except (FileNotFoundError, ValueError) as err:
        print(f"cicfw: error: {err}", file=sys.stderr)
        return 2
    if not chosen:  # e.g. the default, failures, of a run without one: say so rather than exit in silence
        print(f"no episode to film in {args.run_dir}: {' '.join(args.episodes)} selects none of its "
              f"{len(run.rows)} episodes", file=sys.stderr)
        return 0
    # a town file's long stem (which evaluate takes without maps or videos) is one line now, not a write error
    # after the first film is rendered
    limit = name_max(Path(args.run_dir))
    long = [r for r in chosen if film_name_bytes(r["key"]) > limit]
    if long:
        print(f"cicfw: error: episode {long[0]['key']!r} cannot be filmed: its town {long[0]['town']!r} makes a video "
              f"file name longer than this filesystem allows ({limit} bytes)", file=sys.stderr)
        return 2
    towns = {town_label(t): str(t) for t in run.meta.get("suite", {}).get("towns", [])}
    for r in chosen:
        path = film_path(args.run_dir, r["key"])
        write_video(path, r, trajs[r["key"]], load_town(towns.get(r["town"], r["town"])), r["weather"],
                    int(run.meta.get("seed", 0)), family=run_weather_family(run.meta))
        print(path)
    return 0


if __name__ == "__main__":
    install_app_handlers()  # a closed or full stdout: cicfw/core/errors.py, GuardedStdout
    raise SystemExit(main())
