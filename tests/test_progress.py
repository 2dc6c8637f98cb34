"""The project's progress bar: what the collection's and the runner's bars show, and silence when disabled."""
from __future__ import annotations

from cicfw.benchmark.runner import EpisodeBar
from cicfw.core.progress import ProgressBar


def test_the_bar_shows_its_label_count_and_unit(capsys):
    bar = ProgressBar(True, 10, "collect ds", "samples")
    bar.advance(4)
    bar.close()
    out = capsys.readouterr().out
    assert "collect ds" in out and "4/10 samples" in out and "eta" in out, out


def test_the_runners_bar_shows_the_running_success_rate(capsys):
    bar = EpisodeBar(3, "expert")
    bar.update(True)
    bar.update(False)
    bar.close()
    out = capsys.readouterr().out
    assert "expert" in out and "2/3 episodes, success 50.0%" in out, out
    assert (bar.done, bar.ok) == (2, 1)


def test_a_disabled_bar_prints_nothing(capsys):
    bar = ProgressBar(False, 10, "collect ds", "samples")
    bar.advance(4)
    bar.close()
    episodes = EpisodeBar(3, "expert", enabled=False)
    episodes.update(True)
    episodes.close()
    assert capsys.readouterr() == ("", "")
