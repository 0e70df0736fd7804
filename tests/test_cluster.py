"""The one Dask engine's progress: the time left it shows (a missing scheduler: tests/test_sweep.py)."""

from phantom.model import cluster
from phantom.model.cluster import stderr_progress


def test_progress_shows_the_time_left_at_this_runs_rate_not_counting_work_found_done(monkeypatch, capsys):
    now = [100.0]
    monkeypatch.setattr(cluster.time, "monotonic", lambda: now[0])
    report = stderr_progress("table")
    report(40, 100)  # a resumed build: 40 points were on disk, none solved in this run yet
    assert "40/100" in capsys.readouterr().err
    now[0] += 30.0
    report(46, 100)  # 6 points in 30 s: 54 left take 270 s
    shown = capsys.readouterr().err
    assert "46/100 30 s, about 270 s left" in shown
    now[0] += 270.0
    report(100, 100)
    shown = capsys.readouterr().err
    assert "100/100 300 s" in shown and "left" not in shown and shown.endswith("\n")

