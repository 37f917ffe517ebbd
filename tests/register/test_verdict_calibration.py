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
    assert (r["within"], r["off"], r["false_accepts"]) == (110, 50, 0)
    assert r["accepted"] == pytest.approx(106 / 110)
    unmatched = [x for x in rows if x["mtre_mm"] is None]
    assert len(unmatched) == 20 and bench.rates(unmatched, VerdictSettings())["registered"] == 0


def test_six_more_held_out_display_chains_have_no_false_accept():
    rows = bench.load_rows([ROWS / "heldout_chains.jsonl"])
    r = bench.rates(rows, VerdictSettings())
    assert (len(rows), r["within"], r["off"], r["false_accepts"]) == (60, 51, 9, 0)
    assert r["accepted"] == pytest.approx(50 / 51)


def test_the_local_similarity_turns_the_one_edge_false_accept_down_and_no_right_one():
    """``linear-bright-95kV`` frame 4 (its field found whole): 153 mm off in depth, the body's
    outline its only edge, every check but the local similarity passed. The check decides no other
    row: every right registration called registered keeps it."""
    rows = bench.load_rows([ROWS / "heldout_chains.jsonl"])
    without = VerdictSettings(min_local_similarity=None)
    caught = [r for r in rows if bench.judge(r["evidence"], without).label == "registered" and not bench._good(r)]
    assert len(caught) == 1 and caught[0]["mtre_mm"] > 100 and caught[0]["condition"].startswith("linear-bright-95kV")
    assert bench.judge(caught[0]["evidence"], VerdictSettings()).label == "doubtful"
    every = bench.load_rows([ROWS / n for n in ("calib.jsonl", "heldout.jsonl", "unmatched.jsonl", "heldout_chains.jsonl")])
    changed = [r for r in every if bench.judge(r["evidence"], without).label != bench.judge(r["evidence"], VerdictSettings()).label]
    assert changed == caught
