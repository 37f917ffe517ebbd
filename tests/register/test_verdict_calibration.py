"""The shipped verdict thresholds are the calibration's choice on the committed rows of known truth
(benchmarks/verdict_rows/), and the held-out rates docs/results.md gives are those rows' rates."""

from __future__ import annotations

import json
import sys

import pytest

from register.engines.search import GlobalSearchSettings
from register.verdict import VerdictSettings
from tests.conftest import REPO, shared_file

sys.path.insert(0, str(REPO / "benchmarks"))
import verdict as bench  # noqa: E402  (benchmarks/verdict.py, not a package)

ROWS = REPO / "benchmarks" / "verdict_rows"


def test_the_shipped_thresholds_are_the_calibrations_choice():
    """On the 120 calibration registrations with --tools off and the 40 no-grid ones of the same
    pelvis (calib_off.jsonl: judged as --search off, without a floor of the similarity), and with the
    120 of --tools detect too. No row is of a method without the search, so ``sure_similarity``
    (its floor) decides none, and the tie goes to its strictest value."""
    rows = bench.load_rows([ROWS / "calib.jsonl", ROWS / "calib_off.jsonl"])
    assert len(rows) == 160 and sum(r["evidence"]["search"] == "off" for r in rows) == 40
    chosen, rates = bench.calibrate(rows)
    assert chosen == VerdictSettings() and chosen.sure_similarity == GlobalSearchSettings.refined_above
    assert rates["false_accepts"] == 0 and rates["accepted"] == pytest.approx((98 + 17) / (106 + 19))
    r = bench.rates(bench.load_rows([ROWS / "calib_off.jsonl"]), VerdictSettings())
    assert (r["within"], r["off"], r["false_accepts"]) == (19, 21, 0) and r["accepted"] == pytest.approx(17 / 19)
    both = bench.load_rows([ROWS / "calib.jsonl", ROWS / "calib_detect.jsonl", ROWS / "calib_off.jsonl"])
    assert len(both) == 280
    chosen, rates = bench.calibrate(both)
    assert chosen == VerdictSettings()
    assert rates["false_accepts"] == 0 and rates["accepted"] == pytest.approx((98 + 101 + 17) / (106 + 109 + 19))
    chosen, _ = bench.calibrate(bench.load_rows([ROWS / "calib.jsonl"]))
    assert chosen == VerdictSettings()


def test_the_default_pipelines_rates_are_the_documented_ones():
    """docs/results.md, "The default pipeline, --tools detect": every held-out set registered with
    detect: 251 of 260 right registrations accepted, no false accept, no paediatric radiograph
    registered; the calibration's 101 of 109."""
    held = ["heldout", "heldout_chains", "heldout5", "heldout6", "unmatched"]
    rows = bench.load_rows([ROWS / f"{n}_detect.jsonl" for n in held])
    r = bench.rates(rows, VerdictSettings())
    assert (r["within"], r["off"], r["false_accepts"]) == (260, 28, 0)
    assert r["accepted"] == pytest.approx(251 / 260)
    unmatched = [x for x in rows if x["mtre_mm"] is None]
    assert len(unmatched) == 20 and bench.rates(unmatched, VerdictSettings())["registered"] == 0
    c = bench.rates(bench.load_rows([ROWS / "calib_detect.jsonl"]), VerdictSettings())
    assert (c["within"], c["false_accepts"]) == (109, 0) and c["accepted"] == pytest.approx(101 / 109)


def test_twenty_frames_of_the_four_conditions_below_95_percent_are_the_documented_ones():
    """docs/results.md, "Twenty frames": per condition of ``heldout20_detect.jsonl`` (with frames
    0-9 of the two training-pelvis conditions from ``heldout_detect.jsonl`` / ``heldout6_detect.jsonl``),
    the default pipeline's right registrations, those called registered, the wrong ones and the
    false accepts; every right frame doubted is doubted for its depth."""
    from register.verdict import judge

    new = bench.load_rows([ROWS / "heldout20_detect.jsonl"])
    old = bench.load_rows([ROWS / "heldout_detect.jsonl", ROWS / "heldout6_detect.jsonl"])
    want = {"bright-130kV": (20, 18, 0), "linear-70kV": (18, 16, 2), "metal-linear-90kV": (19, 19, 1),
            "tools-linear-110kV": (12, 11, 6)}
    for target, (within, accepted, off) in want.items():
        rows = [r for r in new if r["condition"].startswith(target + ",") and ", default," in r["condition"]]
        if target in ("bright-130kV", "tools-linear-110kV"):  # frames 0-9 registered before
            rows += [r for r in old if r["condition"].startswith(target + ",") and ", default," in r["condition"]]
        r = bench.rates(rows, VerdictSettings())
        assert (r["within"], r["off"], r["false_accepts"]) == (within, off, 0), target
        assert round(r["accepted"] * within) == accepted, target
        for row in rows:
            verdict = judge(row["evidence"], VerdictSettings())
            if bench._good(row) and verdict.label != "registered":
                assert all("depth" in reason for reason in verdict.reasons), (target, verdict.reasons)


def test_calibrated_on_detect_alone_the_profile_would_go_and_three_wrong_poses_pass():
    """Why both sets: the 120 detect registrations alone hold no wrong pose the depth profile must
    reject, so --calibrate drops it; three held-out poses it rejects would then be registered."""
    chosen, _ = bench.calibrate(bench.load_rows([ROWS / "calib_detect.jsonl"]))
    assert chosen.min_profile_drop is None
    wrong = [r for n in ("heldout_chains", "heldout5") for r in bench.load_rows([ROWS / f"{n}_detect.jsonl"])
             if not bench._good(r) and bench.judge(r["evidence"], chosen).label == "registered"]
    assert sorted(round(r["mtre_mm"], 1) for r in wrong) == [13.3, 38.6, 103.3]
    assert all(bench.judge(r["evidence"], VerdictSettings()).label == "doubtful" for r in wrong)


def test_the_held_out_rates_are_the_documented_ones():
    rows = bench.load_rows([ROWS / "heldout.jsonl", ROWS / "unmatched.jsonl"])
    r = bench.rates(rows, VerdictSettings())
    assert (r["within"], r["off"], r["false_accepts"]) == (139, 21, 0)
    assert r["accepted"] == pytest.approx(131 / 139)
    unmatched = [x for x in rows if x["mtre_mm"] is None]
    assert len(unmatched) == 20 and bench.rates(unmatched, VerdictSettings())["registered"] == 0


def test_six_more_held_out_display_chains_have_no_false_accept():
    rows = bench.load_rows([ROWS / "heldout_chains.jsonl"])
    r = bench.rates(rows, VerdictSettings())
    assert (len(rows), r["within"], r["off"], r["false_accepts"]) == (60, 58, 2, 0)
    assert r["accepted"] == pytest.approx(56 / 58)


def test_a_fifth_held_out_set_measured_once_has_no_false_accept_and_accepts_every_right_one():
    rows = bench.load_rows([ROWS / "heldout5.jsonl"])
    r = bench.rates(rows, VerdictSettings())
    assert (len(rows), r["within"], r["off"], r["false_accepts"], r["accepted"]) == (30, 28, 2, 0, 1.0)


def test_a_sixth_held_out_set_with_tools_has_no_false_accept_with_the_rivals_depth_rule(monkeypatch):
    """``studies/heldout6.toml`` (two sets of metal tools, two more chains; 39 registrations, one
    frame refused for its field): one registration 12.2 mm off, mostly in depth, had a rival 13 mm
    deeper scoring 0.034 more; with the runner-up's 20 mm for a distinct depth it was called
    registered, with :data:`register.verdict.RIVAL_DISTINCT_DEPTH_MM` (10 mm) it is doubtful."""
    from register import verdict

    rows = bench.load_rows([ROWS / "heldout6.jsonl"])
    r = bench.rates(rows, VerdictSettings())
    assert (len(rows), r["within"], r["off"], r["false_accepts"]) == (39, 34, 5, 0)
    assert r["accepted"] == pytest.approx(32 / 34)
    caught = [x for x in rows if 12 < x["mtre_mm"] < 12.5]
    assert len(caught) == 1 and 10 < caught[0]["evidence"]["rival"]["depth_mm"] < verdict.DISTINCT_DEPTH_MM
    assert bench.judge(caught[0]["evidence"], VerdictSettings()).label == "doubtful"
    monkeypatch.setattr(verdict, "RIVAL_DISTINCT_DEPTH_MM", verdict.DISTINCT_DEPTH_MM)  # the rule as it was
    assert bench.judge(caught[0]["evidence"], VerdictSettings()).label == "registered"


def test_the_one_edge_frames_are_searched_again_and_judged_by_local_similarity():
    """``linear-bright-95kV`` (a linear bone-bright display: the body's outline over black air its
    strongest edge): the five frames whose pose the whole image's similarity held 46-153 mm off by
    that outline were searched again by local similarity, each to within 5 mm of the truth, and
    judged by it (registered); the five right ones were not searched again."""
    import json

    rows = [json.loads(line) for line in (ROWS / "heldout_chains.jsonl").read_text().splitlines()
            if '"linear-bright-95kV"' in line]
    assert len(rows) == 10 and all(r["mtre_mm"] < 10 for r in rows)
    rescued = [r for r in rows if (r["result"]["search"].get("rescue") or {}).get("kept") == "rescued"]
    assert len(rescued) == 5 and all(r["mtre_mm"] < 5 for r in rescued)
    for r in rescued:
        rescue, ev = r["result"]["search"]["rescue"], r["result"]["verdict_evidence"]
        assert rescue["local_before"] < rescue["local_below"] <= rescue["local_after"]
        assert ev["similarity_metric"] == "local_gncc" and bench.judge(ev, VerdictSettings()).label == "registered"
    assert all(r["result"]["verdict_evidence"]["similarity_metric"] != "local_gncc" for r in rows if r not in rescued)


def test_the_search_again_by_local_similarity_is_summarised_as_documented():
    """docs/results.md's numbers of the pipeline's step 6 in these rows (benchmarks/verdict.py
    --rescues): where it ran, what it moved, how far off before (the recorded first winner against
    the truth, so the CTs are needed) and after."""
    shared_file("ct/pelvis_abdomen_3mm.nii.gz")
    shared_file("ct/pelvis_chiconasa_2mm.nii.gz")
    said = bench.rescues([ROWS / f"{name}.jsonl" for name in ("calib", "heldout", "heldout_chains", "unmatched")])
    assert said.startswith("the search again by local similarity ran on 73 of 340 registrations (median 10.9 s")
    assert "and moved 47 poses" in said and "43 within 10 mm (39 called registered), 4 not" in said
    assert "linear-70kV case 4: 164.9 -> 10.2 mm (doubtful)" in said and "moved off" not in said
    # its "before" errors come from bench._errors: on the final poses it gives the mTRE that
    # benchmarks/search.py recorded for them when it registered them (a round trip through the truth)
    import json

    import numpy as np

    cache: dict = {}
    rows = [json.loads(line) for line in (ROWS / "calib.jsonl").read_text().splitlines()]
    for row in [r for r in rows if (r["result"]["search"].get("rescue") or {}).get("kept") == "rescued"][:4]:
        _, volume, center = bench._ct(row, cache, "test")
        got = bench._errors(row, np.array(row["result"]["pose_4x4"]), volume, center, cache)
        assert got["mtre_mm"] == pytest.approx(row["mtre_mm"], rel=1e-6)


def test_the_tool_segmenters_registrations_are_the_documented_ones():
    """docs/xray_input.md, "Metal tools": the default pipeline with ``--tools detect`` on 13
    conditions of the training pelvis (``tools_detect.jsonl``) against the same frames with
    ``--tools off`` (the verdict tables' rows): within 10 mm / called registered / false accepts."""
    def counts(rows):
        out = {}
        for r in rows:
            name = r["condition"].split(",")[0]
            c = out.setdefault(name, [0, 0, 0])
            label = bench.judge(r["evidence"], VerdictSettings()).label
            good = bench._good(r)
            c[0] += good
            c[1] += good and label == "registered"
            c[2] += (not good) and label == "registered"
        return out

    detect = counts(bench.load_rows([ROWS / "tools_detect.jsonl"]))
    off = counts([r for r in bench.load_rows([ROWS / f"{n}.jsonl" for n in ("calib", "heldout", "heldout6")])
                  if r["condition"].endswith("default") and "chiconasa" not in r["condition"]])
    tools = ("metal-log-75kV", "metal-linear-90kV", "tools-bright-85kV", "tools-linear-110kV")
    assert [detect[n][:2] for n in tools] == [[10, 10], [7, 5], [10, 10], [5, 4]]
    assert [off[n][:2] for n in tools] == [[9, 9], [6, 4], [8, 7], [6, 5]]
    # without tools: the same but one verdict (the attenuation check gave back the air edges that
    # cost linear-70kV two frames and a false accept before it)
    free = [n for n in detect if n not in tools]
    assert [detect[n] for n in free if detect[n] != off[n]] == [[10, 8, 0]] and off["bright-130kV"] == [10, 9, 0]
    assert len(detect) == 13 and sum(c[0] for c in detect.values()) == 120 and sum(c[1] for c in detect.values()) == 113
    assert sum(off[n][0] for n in detect) == 117 and sum(off[n][1] for n in detect) == 110
    assert sum(c[2] for c in detect.values()) == 0


def test_a_rows_tools_are_read_from_the_row_whatever_the_default():
    """--rejudge finishes a row with the tools it was registered with: its key, its method's name,
    and "off" for the committed rows made before either (none of calib.jsonl names detect)."""
    assert bench.row_tools({"tools": "detect", "method": "contextual+cmaes"}) == "detect"
    assert bench.row_tools({"method": "contextual+cmaes (default network), tools detect"}) == "detect"
    assert bench.row_tools({"method": "contextual+cmaes (default network)"}) == "off"
    assert bench.row_tools({"target": "unmatched X-ray"}) == "off"
    raw = [json.loads(line) for line in (ROWS / "calib.jsonl").read_text().splitlines()]
    assert {bench.row_tools(r) for r in raw} == {"off"}
    raw = [json.loads(line) for line in (ROWS / "tools_detect.jsonl").read_text().splitlines()]
    assert {bench.row_tools(r) for r in raw} == {"detect"}
    assert all(r["condition"].endswith("default, tools detect") for r in bench.load_rows([ROWS / "tools_detect.jsonl"]))
