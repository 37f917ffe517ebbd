"""The verdict's evidence that needs a CMA-ES (register/verdict.py): the depth profile and the
rival, on a phantom X-ray of known pose (a line DRR, so the truth is the similarity's and the tone
fit's optimum), how the judge and the calibration use them, and the verdict on a recorded pose
judged again without registering (RegistrationRequest.judge)."""

from __future__ import annotations

import sys
from dataclasses import replace

import numpy as np
import pytest

from register.engines.cmaes import CMAESRegistration, along_view_ray
from register.engines.pipeline import REFINE_SETTINGS
from register.engines.result import RegistrationError
from register.verdict import (DEPTH_PROBE_MM, DISTINCT_DEPTH_MM, PROFILE_PIN_MM, RIVAL_DISTINCT_DEPTH_MM, VerdictSettings,
                              depth_profile, judge, pose_gap, rival)
from sim.projection.drr import DRRRenderer, RenderSettings
from sim.projection.geometry import pose_from_params
from tests.conftest import REPO

sys.path.insert(0, str(REPO / "benchmarks"))
import verdict as bench  # noqa: E402  (benchmarks/verdict.py, not a package)

SIZE = (64, 64)
TRUTH = np.array([5.0, -3.0, 2.0, 6.0, -4.0, 10.0])


@pytest.fixture(scope="module")
def scene():
    from sim.ct.anatomy import anatomy_center
    from sim.ct.phantom import make_pelvis_phantom

    vol = make_pelvis_phantom(0, spacing_mm=4.0)
    c = anatomy_center(vol)
    xray = DRRRenderer(vol, RenderSettings(size=SIZE), center_lps=c).render_params(TRUTH)[0]
    refine = CMAESRegistration(vol, replace(REFINE_SETTINGS, size=SIZE, popsize=12), center_lps=c).scored_by(("gncc",))
    return vol, c, xray, refine


def test_the_profile_pins_the_depth_and_falls_from_the_true_pose(scene):
    _, _, xray, refine = scene
    here, scores, poses = depth_profile(refine, xray, TRUTH)
    sod = refine.geometry.sod_mm
    # the X-ray is the DRR at the truth: its gradient NCC there is 1 (to the float sums' rounding)
    assert here == pytest.approx(1.0, abs=1e-9)
    # each fit stays on its probe's depth: the camera depth of the centre within the pinning box
    probes = along_view_ray(TRUTH, [DEPTH_PROBE_MM, -DEPTH_PROBE_MM], sod)
    np.testing.assert_allclose(poses[:, 5], probes[:, 5], atol=PROFILE_PIN_MM + 1e-9)
    # no rigid pose 30 mm nearer or farther makes the same image (the magnification changes by
    # 4-5 %): the profile falls, though less than far off (the fit makes up some of it)
    assert np.all(scores < here - 0.02) and np.all(scores > 0.2)
    # at least the moved pose's own score (the fit runs at half resolution and may end below it)
    from register.engines.metrics import gradient_ncc

    plain = gradient_ncc(xray, refine.render(probes))
    assert np.all(scores >= plain) and np.all(scores < 1.0)


def test_the_rival_finds_the_joint_optimum_and_gains_nothing_at_it(scene):
    _, _, xray, refine = scene
    sod = refine.geometry.sod_mm
    at_truth = rival(refine, xray, TRUTH)
    # the X-ray is the DRR at the truth: similarity and tone fit are both 1 there, so nothing beats it
    assert at_truth["gain"] == pytest.approx(0.0, abs=1e-6)
    assert at_truth["similarity"] == pytest.approx(1.0, abs=1e-9) and at_truth["tone_fit"] == pytest.approx(1.0, abs=1e-9)
    # from a pose 3 deg and 25 mm in depth off, edges and intensities together lead back towards the truth
    off = TRUTH + np.array([0.0, 3.0, 0.0, 0.0, 0.0, 25.0])
    found = rival(refine, xray, off)
    assert found["gain"] > 0.05 and found["similarity"] > 0.8 and found["tone_fit"] > 0.95
    before = pose_gap(pose_from_params(off, sod), pose_from_params(TRUTH, sod))
    assert found["depth_mm"] > 0.5 * before[2]  # it moved most of the way in depth
    # a display image (its toned version given): the edges are scored display-tolerantly, and a
    # monotone tone curve changes neither optimum
    display = np.sqrt(xray - xray.min())
    assert rival(refine, display, TRUTH, toned=xray)["gain"] == pytest.approx(0.0, abs=1e-6)


def test_adjusted_shares_the_renderers_and_refuses_a_level_it_does_not_render(scene):
    _, _, _, refine = scene
    other = refine.adjusted(generations=(5,))
    assert other.by_factor is refine.by_factor and other.settings.generations == (5,)
    assert refine.settings.generations == REFINE_SETTINGS.generations
    with pytest.raises(RegistrationError, match="no renderer for the level"):
        refine.adjusted(levels=(8,))
    with pytest.raises(RegistrationError, match="the size stays"):
        refine.adjusted(size=(32, 32))


def _ev(**kw) -> dict:
    ev = {"similarity": 0.9, "tone_fit": 0.8, "runner_up": None, "search": "ran", "field_fraction": 0.5}
    ev.update(kw)
    return ev


def test_the_judge_uses_the_profile_and_the_rival_only_with_thresholds():
    flat = _ev(depth_profile={"drop": 0.01, "similarity": 0.9, "scores": [0.89, 0.85]})
    other = _ev(rival={"similarity": 0.85, "tone_fit": 0.99, "gain": 0.14, "deg": 10.0, "mm": 9.0, "depth_mm": 9.0})
    off = VerdictSettings(min_profile_drop=None, max_rival_gain=None)
    assert judge(flat, off).label == "registered" and judge(other, off).label == "registered"  # None: not judged
    s = VerdictSettings(min_profile_drop=0.04, max_rival_gain=0.1)
    v = judge(flat, s)
    assert v.label == "doubtful" and "fitted again" in v.reasons[0]
    v = judge(other, s)
    assert v.label == "doubtful" and "scores 0.14 higher on similarity and tone fit together" in v.reasons[0]
    assert judge(other, VerdictSettings(min_profile_drop=0.04, max_rival_gain=0.15)).label == "registered"
    # a gain at a pose that is not distinct is the same answer refined
    same = _ev(rival={"similarity": 0.85, "tone_fit": 0.99, "gain": 0.2, "deg": 1.0, "mm": 2.0, "depth_mm": 5.0})
    assert judge(same, s).label == "registered"
    with pytest.raises(RegistrationError, match="min_profile_drop"):
        VerdictSettings(min_profile_drop=float("nan"))


def test_the_calibration_judges_the_new_evidence_only_where_rows_have_it():
    good = [{"condition": "c", "mtre_mm": 1.0, "evidence": _ev(similarity=0.8 + 0.01 * i,
                                                              depth_profile={"drop": 0.1 + 0.01 * i})} for i in range(5)]
    # a wrong pose every old check passes: only the profile tells it
    wrong = {"condition": "c", "mtre_mm": 45.0, "evidence": _ev(similarity=0.95, depth_profile={"drop": 0.03})}
    chosen, r = bench.calibrate(good + [wrong])
    assert r["false_accepts"] == 0 and r["accepted"] == 1.0
    assert 0.03 < chosen.min_profile_drop <= 0.1 and chosen.max_rival_gain is None  # no row has a rival
    without = [{**x, "evidence": {k: v for k, v in x["evidence"].items() if k != "depth_profile"}} for x in good]
    chosen, _ = bench.calibrate(without)
    assert chosen.min_profile_drop is None


def test_the_calibration_keeps_a_margin_from_a_clearly_wrong_pose_only():
    # right poses down to 0.28; one wrong pose that only its similarity, 0.248, tells: a floor of 0.25
    # accepts every right one and rejects it, but by 0.002. 24.6 mm off (clearly wrong: >= 15 mm), the
    # floor must still reject it 10 % lower (0.225): the 0.28 pose is lost, and of the floors that keep
    # the other three the strictest, 0.5, is chosen; 12 mm off (just past the bar), rejecting it is enough
    right = [{"condition": "c", "mtre_mm": 2.0, "evidence": _ev(similarity=s)} for s in (0.28, 0.5, 0.7, 0.9)]
    for mtre, floor, accepted in ((24.6, 0.5, 0.75), (12.0, 0.25, 1.0)):
        wrong = {"condition": "c", "mtre_mm": mtre, "evidence": _ev(similarity=0.248)}
        chosen, r = bench.calibrate(right + [wrong])
        assert (chosen.min_similarity, r["false_accepts"], r["accepted"]) == (floor, 0, accepted), mtre
    assert bench.CLEARLY_OFF_MM == 1.5 * bench.WITHIN_MM and bench._looser("max_rival_gain", 0.03) == pytest.approx(0.033)
    assert bench._looser("min_joint_margin", -0.05) == pytest.approx(-0.055) and bench._looser("min_local_similarity", None) is None


@pytest.mark.parametrize("depth_mm, gain, label", [(13.0, 0.034, "doubtful"),   # past the bar in depth, clearly better
                                                    (9.0, 0.034, "registered"),  # within the bar: the same answer
                                                    (13.0, 0.02, "registered"),  # not clearly better
                                                    (25.0, 0.05, "doubtful")])   # distinct as a runner-up would be
def test_a_rival_counts_ten_mm_away_in_depth_alone(depth_mm, gain, label):
    assert RIVAL_DISTINCT_DEPTH_MM == 10.0 < DISTINCT_DEPTH_MM
    rival_pose = {"similarity": 0.55, "tone_fit": 0.9, "gain": gain, "deg": 0.7, "mm": 0.3, "depth_mm": depth_mm}
    v = judge(_ev(rival=rival_pose), VerdictSettings(max_rival_gain=0.03))
    assert v.label == label


def test_a_pose_that_shows_no_ct_is_profiled_without_a_fit_and_has_no_rival(scene):
    # an untrained network may end anywhere: the evidence is still gathered, and the similarity fails it
    _, _, xray, refine = scene
    away = np.array([0.0, 0.0, 0.0, 3000.0, 0.0, 0.0])
    assert not refine.in_view(away)[0]
    here, scores, poses = depth_profile(refine, xray, away)
    np.testing.assert_allclose(poses, along_view_ray(away, [DEPTH_PROBE_MM, -DEPTH_PROBE_MM], refine.geometry.sod_mm))
    assert abs(here) < 0.05 and np.all(np.abs(scores) < 0.05)
    assert rival(refine, xray, away) is None


def test_a_runner_up_as_good_on_edges_and_intensities_together_is_judged_only_with_a_joint_margin():
    # the runner-up scores less on edges but more on intensities: 0.87 + 0.9 against 0.9 + 0.85
    runner = {"similarity": 0.87, "deg": 12.0, "mm": 5.0, "depth_mm": 40.0, "index": 1, "tone_fit": 0.9}
    ev = _ev(similarity=0.9, tone_fit=0.85, runner_up=runner)
    assert judge(ev, VerdictSettings(min_joint_margin=None)).label == "registered"  # None: not judged
    v = judge(ev, VerdictSettings(min_joint_margin=0.0))
    assert v.label == "doubtful" and "scores as well on similarity and tone fit together: this pose -0.02" in v.reasons[0]
    v = judge(ev, VerdictSettings(min_joint_margin=-0.05))  # the runner-up may score up to 0.05 more
    assert v.label == "registered" and any("similarity plus tone fit -0.02 against the runner-up's" in r for r in v.reasons)
    # a runner-up without its tone fit (rows recorded before it) is judged on its similarity alone
    no_tone = _ev(similarity=0.9, tone_fit=0.85, runner_up={k: v for k, v in runner.items() if k != "tone_fit"})
    assert judge(no_tone, VerdictSettings(min_joint_margin=0.05)).label == "registered"


def test_the_runner_up_carries_its_tone_fit_and_judge_result_renders_every_refined_start():
    from register.engines.result import RegistrationResult
    from register.verdict import judge_result, runner_up

    sod = 700.0
    final = np.zeros(6)
    starts = [final.tolist(), [0.0, 0.0, 12.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0, 0.0, 50.0]]
    search = {"grid_poses": 10, "refined": [0.9, 0.85, 0.88], "refined_params": starts}
    ru = runner_up(search, pose_from_params(final, sod), sod, [0.8, 0.7, 0.3])
    assert ru["index"] == 2 and ru["tone_fit"] == 0.3 and ru["depth_mm"] == pytest.approx(50.0)
    # the line renderer given: the X-ray itself at the final pose (tone fit 1), its negative
    # elsewhere (tone fit -1)
    image = np.random.default_rng(3).random((24, 24))
    T = pose_from_params(final, sod)

    def line(poses):
        return np.array([image if np.allclose(p, T) else -image for p in np.asarray(poses).reshape(-1, 4, 4)])

    res = RegistrationResult(params=final, pose=T, projection=np.eye(3, 4), similarity=0.9, renders=1,
                             stage_seconds={}, search=search)
    v = judge_result(res, image, render=line, sod_mm=sod)
    assert v.evidence["refined_tones"] == pytest.approx([1.0, -1.0, -1.0])
    assert v.evidence["runner_up"]["tone_fit"] == pytest.approx(-1.0) and v.evidence["runner_up"]["index"] == 2


def test_the_calibration_tries_the_joint_margin_where_the_runner_ups_have_tone_fits():
    def row(mtre, sim, tone, ru_sim, ru_tone):
        return {"condition": "c", "mtre_mm": mtre,
                "evidence": _ev(similarity=sim, tone_fit=tone, refined_tones=[tone, ru_tone],
                                runner_up={"similarity": ru_sim, "deg": 10.0, "mm": 5.0, "depth_mm": 30.0,
                                           "index": 1, "tone_fit": ru_tone})}
    # right poses whose runner-ups fit the intensities far worse; a wrong one whose runner-up fits
    # them better, so that it scores more on the two together, though less on edges
    rows = [row(1.0, 0.9, 0.9, 0.88, 0.5), row(2.0, 0.85, 0.8, 0.84, 0.55), row(40.0, 0.9, 0.8, 0.85, 0.9)]
    chosen, r = bench.calibrate(rows)
    assert r["false_accepts"] == 0 and r["accepted"] == 1.0
    assert chosen.min_joint_margin is not None and -0.05 <= chosen.min_joint_margin <= 0.05
    # without the runner-ups' tone fits the margin on edges alone must do it (0.05 for the wrong
    # one, 0.02 and 0.01 for the right ones): no false accept, and the right ones doubtful
    plain = [{**x, "evidence": {**x["evidence"], "refined_tones": None,
                                "runner_up": {k: v for k, v in x["evidence"]["runner_up"].items() if k != "tone_fit"}}}
             for x in rows]
    chosen, r = bench.calibrate(plain)
    assert chosen.min_joint_margin is None and r["false_accepts"] == 0 and r["accepted"] == 0.0


def test_a_recorded_pose_judged_again_gives_the_registration_s_own_evidence(phantom_xray):
    """RegistrationRequest.judge (benchmarks/verdict.py --rejudge) prepares the X-ray as the
    registration did and gathers the same evidence at its pose, without registering."""
    from register.api import RegistrationRequest, register_xray

    vol, c, xray = phantom_xray
    done = register_xray(vol, xray, method="cmaes", restarts=0, center=c, size=(32, 32))
    request = RegistrationRequest(method="cmaes", restarts=0, center=c, size=(32, 32))
    again = request.judge(vol, xray, done.result.params, similarity=done.result.similarity, search=done.result.search)
    assert again.label == done.verdict.label and again.reasons == done.verdict.reasons
    assert again.evidence == done.verdict.evidence  # every number, to the bit (no network: no gap either)
    with pytest.raises(RegistrationError, match="six finite numbers"):
        request.judge(vol, xray, [0.0, np.nan, 0, 0, 0, 0], similarity=0.5)
    with pytest.raises(RegistrationError, match="similarity must be finite"):
        request.judge(vol, xray, done.result.params, similarity=float("nan"))


@pytest.fixture(scope="module")
def phantom_xray(scene):
    from register.xray.io import XRayImage

    vol, c, _, _ = scene
    r = DRRRenderer(vol, RenderSettings(size=SIZE), center_lps=c)
    g = r.geometry
    image = r.render_params(TRUTH + np.array([2.0, 0.0, 0.0, 4.0, 0.0, 0.0]))[0]
    return vol, c, XRayImage(image, pixel_spacing_mm=g.pixel_spacing_mm, sdd_mm=g.sdd_mm, sod_mm=g.sod_mm, source="drr")


def test_rejudge_refuses_a_row_whose_ct_is_not_here(tmp_path, capsys):
    import json

    row = {"target": "fluoro-65kV", "study": "studies/domain_gap.toml", "case": 0, "ct": str(tmp_path / "no.nii.gz"),
           "mtre_mm": 1.0, "result": {"params": dict.fromkeys(("phi", "theta", "psi", "tx", "ty", "tz"), 0.0),
                                      "similarity": 0.9, "verdict_evidence": {"search": "none"}}}
    src = tmp_path / "rows.jsonl"
    src.write_text(json.dumps(row) + "\n")
    with pytest.raises(SystemExit) as e:
        bench.rejudge(src, tmp_path / "out.jsonl", tmp_path / "frames")
    assert e.value.code == 2 and "the CT of a row (fluoro-65kV, case 0) is not here" in capsys.readouterr().err
    assert not (tmp_path / "out.jsonl").exists()
