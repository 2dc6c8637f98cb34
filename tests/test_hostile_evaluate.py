"""``cicfw evaluate`` as a hostile user runs it (issue 17): mistakes refused before any episode is
driven."""
from __future__ import annotations

from pathlib import Path

import pytest

from cicfw.bench.journal import LOG_NAME
from cicfw.evaluate import compose_config, evaluate

TOWN = str(Path(__file__).parent / "data" / "bench_town.yaml")
QUICK = ("policy=expert", f"suite.towns=[{TOWN}]", "suite.weathers=[ClearNoon]", "suite.limit=2",
         "progress_bar=false", "runner.workers=1")


@pytest.mark.parametrize("override, message", [
    ("+foo=1", "unknown top-level key 'foo'; accepted top-level keys: checkpoint, maps, name, policy, progress_bar, "
               "runner, seed, sim, suite, video, video_max"),
    ("+vide=[0]", "unknown top-level key 'vide'; did you mean 'video'? accepted top-level keys: checkpoint,"),
])
def test_an_unknown_top_level_key_is_refused_before_driving(tmp_path, override, message):
    with pytest.raises(ValueError) as err:
        evaluate(compose_config([*QUICK, override]), tmp_path / "run")
    assert str(err.value).startswith(message) and "\n" not in str(err.value), str(err.value)
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("video, message", [
    ("[nosuch]", "video: unknown episode 'nosuch'; give episode indices, keys such as bench_town/ClearNoon/000, "
                 "bench_town/ClearNoon/001, or 'failures'"),
    ("[5]", "video: no episode 5 in this run (episodes 0..1)"),
    ("3", "video must be a list of episodes (indices, keys such as town_a/ClearNoon/003, or 'failures'), got 3"),
])
def test_an_unknown_video_episode_is_refused_before_driving(tmp_path, video, message):
    with pytest.raises(ValueError) as err:
        evaluate(compose_config([*QUICK, f"video={video}"]), tmp_path / "run")
    assert str(err.value) == message
    assert not (tmp_path / "run" / LOG_NAME).exists()  # not one episode driven
