"""The shipped verdict thresholds are the calibration's choice on the committed rows of known truth
(benchmarks/verdict_rows/), and the held-out rates docs/results.md gives are those rows' rates."""

from __future__ import annotations

import sys

import pytest

from register.verdict import VerdictSettings
from tests.conftest import REPO

sys.path.insert(0, str(REPO / "benchmarks"))
import verdict as bench  # noqa: E402  (benchmarks/verdict.py, not a package)

ROWS = REPO / "benchmarks" / "verdict_rows"


def test_the_shipped_thresholds_are_the_calibrations_choice():
    rows = bench.load_rows([ROWS / "calib.jsonl"])
    assert len(rows) == 120
    chosen, rates = bench.calibrate(rows)
    assert chosen == VerdictSettings()
    assert rates["false_accepts"] == 0 and rates["accepted"] == pytest.approx(91 / 94)


def test_the_held_out_rates_are_the_documented_ones():
    rows = bench.load_rows([ROWS / "heldout.jsonl", ROWS / "unmatched.jsonl"])
    r = bench.rates(rows, VerdictSettings())
    assert (r["within"], r["off"], r["false_accepts"]) == (108, 52, 0)
    assert r["accepted"] == pytest.approx(104 / 108)
    unmatched = [x for x in rows if x["mtre_mm"] is None]
    assert len(unmatched) == 20 and bench.rates(unmatched, VerdictSettings())["registered"] == 0


def test_six_more_held_out_display_chains_have_no_false_accept():
    rows = bench.load_rows([ROWS / "heldout_chains.jsonl"])
    r = bench.rates(rows, VerdictSettings())
    assert (len(rows), r["within"], r["off"], r["false_accepts"]) == (60, 51, 9, 0)
    assert r["accepted"] == pytest.approx(50 / 51)
