"""benchmarks/compare_runs.py: runs side by side at the checks they share, pairs = iterations x
batch size, each run's rate; the plot's legend below the panels; bad arguments refused in a line."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from tests.conftest import load_benchmark


@pytest.fixture(scope="module")
def cr():
    return load_benchmark("compare_runs")


def _log(path: Path, rows: list[tuple]) -> str:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["iteration", "train_loss", "val_rot_err_deg", "val_trans_err_mm", "elapsed_s",
                    "val_rot_ap_deg", "val_trans_ap_mm"])
        w.writerows(rows)
    return str(path)


def test_the_table_shows_the_shared_checks_at_equal_pairs(cr, tmp_path, capsys):
    a = _log(tmp_path / "a.csv", [(100, 0.3, 40.0, 100.0, 50, 50.0, 140.0), (200, 0.2, 30.0, 80.0, 100, 45.0, 120.0)])
    b = _log(tmp_path / "b.csv", [(200, 0.2, 35.0, 90.0, 400, 48.0, 130.0), (300, 0.1, 20.0, 60.0, 600, 40.0, 110.0)])
    png = tmp_path / "c.png"
    assert cr.main([f"A={a}", f"B={b}", "--batch-size", "256", "--groups", "all", "ap", "--plot", str(png),
                    "--baseline", "all=41.1/105.7"]) == 0
    out = capsys.readouterr().out
    lines = [ln for ln in out.splitlines() if ln.startswith("| ")]
    assert lines[1] == "| 51 k | 30.0 / 80.0 | 35.0 / 90.0 | 45.0 / 120.0 | 48.0 / 130.0 |"  # only iteration 200
    assert "| A | 51 k | 100 | 512 |" in out and "| B | 77 k | 600 | 128 |" in out  # pairs / s = 51200 / 100
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_bad_arguments_are_refused_in_a_line(cr, tmp_path, capsys):
    with pytest.raises(SystemExit, match="NAME=PATH/log.csv"):
        cr.main(["no-equals-sign"])
    with pytest.raises(SystemExit, match="cannot be read"):
        cr.main([f"A={tmp_path / 'missing.csv'}"])
    a = _log(tmp_path / "a.csv", [(100, 0.3, 40.0, 100.0, 50, 50.0, 140.0)])
    assert cr.main([f"A={a}", "--baseline", "all=41"]) == 2
    assert "give GROUP=ROT/TRANS" in capsys.readouterr().err
