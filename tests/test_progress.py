"""The progress line of long commands (sim.core.progress.Progress): counts, rate, ETA, and where it goes."""

from __future__ import annotations

import re

import pytest

from sim.core.progress import Progress, StageClock, process_seconds


def test_progress_line_counts_rate_and_eta(capsys, monkeypatch):
    clock = [100.0]
    monkeypatch.setattr("sim.core.progress.time.monotonic", lambda: clock[0])
    bar = Progress(10, 2, "train x", "iterations", rate_unit="pairs/s", rate_scale=32)  # resumed at 2 of 10
    first = capsys.readouterr().err
    assert first.startswith("train x: 2/10 iterations ( 20.0 %)") and "ETA --" in first
    clock[0] += 4.0
    bar.update(4)  # 4 iterations in 4 s: 1 it/s = 32 pairs/s; 4 left: 4 s
    assert capsys.readouterr().err == ""  # not a terminal: a line every 5 s at most
    clock[0] += 1.0
    bar.update(1)  # 5 in 5 s: 32 pairs/s, 3 left
    line = capsys.readouterr().err.strip()
    assert re.fullmatch(r"train x: 7/10 iterations \( 70\.0 %\),\s+32\.0 pairs/s, ETA 00:00:03", line), line
    bar.update(3)  # the end is always shown
    assert "10/10 iterations (100.0 %)" in capsys.readouterr().err


def test_a_training_run_shows_its_progress_on_stderr(tmp_path, capsys):
    from pathlib import Path

    from learn.train import TrainConfig, train

    root = Path(__file__).resolve().parents[1]
    cfg = TrainConfig(dataset=str(root / "campaigns" / "smoke.toml"), out=str(tmp_path / "t"), iterations=2,
                      batch_size=2, val_pairs=2, val_every=2, checkpoint_every=2, head_channels=8)
    train(cfg, log=lambda s: None)
    err = capsys.readouterr().err
    assert "train t: 0/2 iterations" in err and "train t: 2/2 iterations (100.0 %)" in err and "pairs/s" in err


def test_the_stage_clock_sums_each_stage_in_the_order_they_ran(monkeypatch):
    now = [10.0]
    monkeypatch.setattr("sim.core.progress.time.perf_counter", lambda: now[0])
    clock = StageClock()
    for stage, seconds in (("ct", 1.5), ("register", 2.0), ("ct", 0.25)):
        with clock(stage):
            now[0] += seconds
    assert clock.seconds == {"ct": 1.75, "register": 2.0}
    assert clock.lines() == ["ct: 1.75 s", "register: 2.00 s"]
    with pytest.raises(KeyError):  # a stage that raised still counts its seconds
        with clock("write"):
            now[0] += 0.5
            raise KeyError("x")
    assert clock.seconds["write"] == 0.5
    with clock("register"):  # a stage inside another is its own: the outer one leaves it out
        now[0] += 1.0
        with clock("polarity"):
            now[0] += 3.0
        now[0] += 0.5
    assert clock.seconds["polarity"] == 3.0 and clock.seconds["register"] == 2.0 + 1.5


def test_process_seconds_counts_from_the_process_start():
    """A fresh interpreter that sleeps 0.5 s first says at least that (the /proc clock ticks at
    10 ms), and less than the whole subprocess took."""
    import subprocess
    import sys
    import time

    t0 = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", "import time; time.sleep(0.5); "
                          "from sim.core.progress import process_seconds; print(process_seconds())"],
                         capture_output=True, text=True, check=True)
    took = time.perf_counter() - t0
    assert 0.48 <= float(out.stdout) <= took + 0.02


def test_the_stage_clocks_example_runs():
    import doctest

    import sim.core.progress

    assert doctest.testmod(sim.core.progress).failed == 0


def test_a_time_limit_that_comes_first_gives_the_eta_and_share(capsys, monkeypatch):
    import sim.core.progress as progress

    clock = [100.0]
    monkeypatch.setattr(progress.time, "monotonic", lambda: clock[0])
    bar = Progress(10_000_000, 0, "train x", "iterations", rate_unit="pairs/s", rate_scale=32, time_limit_s=600.0)
    clock[0] += 150.0
    bar.done = 300  # 2 iterations/s: 10 M iterations would take weeks; the limit ends it in 450 s
    line = bar.line()
    assert "train x: 300 iterations ( 25.0 % of 10.0 min)" in line and "ETA 00:07:30" in line and "64.0 pairs/s" in line
    short = Progress(400, 0, "train y", "iterations", time_limit_s=600.0)  # the iterations end first
    clock[0] += 100.0
    short.done = 200
    assert "200/400 iterations" in short.line() and "ETA 00:01:40" in short.line()
