"""The verdict on a registration (register/verdict.py): its evidence from known poses, its rules,
its rates against the truth, and the exit status it sets."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from register.engines.result import RegistrationError, RegistrationResult
from register.evaluation.evaluate import verdict_rates
from register.verdict import (DECISION_MARGIN, DISTINCT_DEG, DISTINCT_DEPTH_MM, DISTINCT_MM, EXIT_STATUS, depth_probe_poses, Verdict, VerdictSettings, gather_evidence, judge,
                              clearly_registered, judge_result, pose_gap)
from sim.projection.geometry import params_from_pose, pose_from_params

SOD = 700.0


def _evidence(**kw) -> dict:
    ev = {"similarity": 0.9, "tone_fit": 0.8, "runner_up": None, "search": "ran", "field_fraction": 0.5}
    ev.update(kw)
    return ev


def test_pose_gap_is_the_rotation_angle_and_the_centre_displacement_across_and_along_the_view():
    a = np.zeros(6)
    b = np.array([0.0, 0.0, 7.0, 3.0, 4.0, -12.0])  # 7 deg about one axis, the centre moved (3, 4, -12) mm
    deg, mm, depth = pose_gap(pose_from_params(a, SOD), pose_from_params(b, SOD))
    assert deg == pytest.approx(7.0, abs=1e-9) and mm == pytest.approx(5.0, abs=1e-9)
    assert depth == pytest.approx(12.0, abs=1e-9)


def test_a_similarity_below_the_floor_fails_whatever_else_holds():
    s = VerdictSettings()
    v = judge(_evidence(similarity=s.fail_below - 0.01), s)
    assert v.label == "failed" and "does not match" in v.reasons[0] and v.exit_status == 3
    v = judge(_evidence(similarity=float("nan")), s)
    assert v.label == "failed"


def test_a_tone_fit_below_its_floor_fails():
    s = VerdictSettings()
    v = judge(_evidence(tone_fit=s.tone_fail_below - 0.05), s)
    assert v.label == "failed" and "intensities disagree" in v.reasons[0]


def test_a_clear_winner_of_the_search_is_registered_and_says_what_was_checked():
    s = VerdictSettings()
    runner = {"similarity": 0.9 - s.min_margin - 0.01, "deg": 12.0, "mm": 40.0}
    v = judge(_evidence(runner_up=runner), s)
    assert v.label == "registered" and v.exit_status == 0
    assert any("no distinct pose" in r for r in v.reasons) and any("tone fit" in r for r in v.reasons)


def test_a_distinct_pose_scoring_alike_makes_it_doubtful():
    s = VerdictSettings()
    runner = {"similarity": 0.9 - s.min_margin + 0.01, "deg": 11.0, "mm": 80.0, "depth_mm": 5.0}
    v = judge(_evidence(runner_up=runner), s)
    assert v.label == "doubtful" and "11 deg, 80 mm across and 5 mm in depth away" in v.reasons[0]


def test_a_method_without_the_search_needs_a_clear_match_and_the_pipeline_without_its_grid_does_not():
    s = VerdictSettings()
    assert s.sure_similarity == 0.88
    for search in ("skipped", "off"):  # contextual+cmaes, its pose refined: the other checks judge it
        v = judge(_evidence(search=search, similarity=0.6), s)
        assert v.label == "registered" and not any("alternative" in r for r in v.reasons), v.reasons
        assert judge(_evidence(search=search, similarity=0.6, local_similarity=s.min_local_similarity - 0.01),
                     s).label == "doubtful"
    assert judge(_evidence(search="none", similarity=0.89), s).label == "registered"
    v = judge(_evidence(search="none", similarity=0.87), s)
    assert v.label == "doubtful" and "no alternative examined (a method without the search)" in v.reasons[0]
    assert judge(_evidence(search="none", similarity=0.6), replace(s, sure_similarity=None)).label == "registered"


def test_a_pose_kept_without_the_grid_must_clear_every_calibrated_threshold_by_the_decision_margin():
    """The held-out pose 14.5 mm off that the pipeline first kept without the grid passed the local
    similarity by 0.004: registered by the verdict, not clearly (every threshold 10 % stricter)."""
    s = VerdictSettings()
    t = s.stricter(DECISION_MARGIN)
    assert DECISION_MARGIN == 0.1 and t.min_local_similarity == pytest.approx(0.385)
    assert t.max_rival_gain == pytest.approx(0.027) and t.min_similarity == pytest.approx(0.44)
    assert t.sure_similarity == pytest.approx(0.968) and (t.fail_below, t.min_field_fraction) == (s.fail_below, s.min_field_fraction)
    assert s.stricter(0.0) == s
    marginal = judge(_evidence(search="skipped", similarity=0.76, local_similarity=0.354), s)
    assert marginal.label == "registered" and not clearly_registered(marginal)
    clear = judge(_evidence(search="skipped", similarity=0.76, local_similarity=0.6), s)
    assert clearly_registered(clear)
    assert not clearly_registered(judge(_evidence(search="skipped", similarity=0.3), s))
    for bad in (1.0, -0.1, True, float("nan")):
        with pytest.raises(RegistrationError, match="margin must be a share"):
            s.stricter(bad)


def test_low_similarity_low_tone_fit_and_a_small_field_each_give_a_doubt():
    s = VerdictSettings()
    v = judge(_evidence(similarity=max(s.min_similarity - 0.01, s.fail_below), tone_fit=s.min_tone_fit - 0.01,
                        field_fraction=s.min_field_fraction / 2), s)
    assert v.label == "doubtful" and len(v.reasons) == 3


@pytest.mark.parametrize("bad", [{"min_margin": float("nan")}, {"fail_below": 2.0}, {"sure_similarity": True}])
def test_settings_out_of_range_are_refused(bad):
    with pytest.raises(RegistrationError, match=next(iter(bad))):
        VerdictSettings(**bad)


def test_the_runner_up_is_the_best_distinct_refined_start_not_the_winner_refined_again():
    final = np.array([5.0, -3.0, 2.0, 10.0, -4.0, 15.0])
    near = final + np.array([DISTINCT_DEG / 2, 0, 0, DISTINCT_MM / 2, 0, 0])  # the same answer, refined apart
    deeper = final + np.array([0, 0, 0, 0, 0, DISTINCT_DEPTH_MM * 0.9])  # the same answer but for the depth
    far = final + np.array([0, 0, 0, 0, 3 * DISTINCT_MM, 0])
    farther = final + np.array([3 * DISTINCT_DEG, 0, 0, 0, 0, 0])
    search = {"refined": [0.80, 0.79, 0.78, 0.70, 0.60],
              "refined_params": [final.tolist(), near.tolist(), deeper.tolist(), far.tolist(), farther.tolist()],
              "grid_poses": 1980}
    T = pose_from_params(final, SOD)
    image = np.random.default_rng(0).random((32, 32))
    ev = gather_evidence(similarity=0.8, pose=T, image=image, mask=None, drr=2 * image + 1, toned=None,
                         search=search, search_ran=True, network_pose=pose_from_params(far, SOD), sod_mm=SOD,
                         field_fraction=0.4)
    assert ev["runner_up"]["similarity"] == pytest.approx(0.70) and ev["runner_up"]["mm"] == pytest.approx(30.0, abs=1e-6)
    assert ev["runner_up"]["depth_mm"] == pytest.approx(0.0, abs=1e-6)
    assert ev["alternatives"] == 4 and ev["search"] == "ran"
    assert ev["tone_fit"] == pytest.approx(1.0)  # a DRR that is the image's affine map: intensities agree
    assert ev["network_gap"]["mm"] == pytest.approx(30.0, abs=1e-3) and ev["network_gap"]["deg"] < 1e-6
    # the toned image, where given, is what the tone fit compares
    ev = gather_evidence(similarity=0.8, pose=T, image=image, mask=None, drr=2 * image + 1, toned=-image,
                         search=None, search_ran=False, network_pose=None, sod_mm=SOD, field_fraction=0.4)
    assert ev["tone_fit"] == pytest.approx(-1.0) and ev["runner_up"] is None and ev["search"] == "none"


def test_judge_result_reads_the_network_pose_from_the_trajectory_and_the_field_from_the_mask():
    final = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    network = np.array([0.0, 0.0, 9.0, 0.0, 0.0, 0.0])
    T = pose_from_params(final, SOD)
    image = np.random.default_rng(1).random((24, 24))
    mask = np.zeros((24, 24), bool)
    mask[:, :12] = True
    res = RegistrationResult(params=final, pose=T, projection=np.eye(3, 4), similarity=0.95, renders=1, stage_seconds={},
                             trajectory={"params": np.array([network * 0.5, network])})
    other = np.random.default_rng(2).random((2, 24, 24))  # what the depth probe's poses see: unlike the X-ray
    v = judge_result(res, image, render=lambda poses: np.concatenate([image[None], other]), sod_mm=SOD, mask=mask)
    assert v.evidence["network_gap"]["deg"] == pytest.approx(9.0, abs=1e-6)
    assert v.evidence["field_fraction"] == pytest.approx(0.5) and v.evidence["search"] == "none"
    assert v.label == "registered"  # similarity 0.95 >= sure_similarity, tone fit 1, the depth probe falls
    assert params_from_pose(T, SOD) == pytest.approx(final)
    assert v.evidence["depth_drop"] > 0.5  # gradient NCC 1 at the pose, about 0 at the probes
    same = judge_result(res, image, render=lambda poses: np.repeat(image[None], len(poses), axis=0), sod_mm=SOD)
    assert same.evidence["depth_drop"] == pytest.approx(0.0) and same.label == "doubtful"  # depth undetermined


def test_the_depth_probe_moves_the_pose_along_the_ray_through_the_centre():
    T = pose_from_params(np.array([5.0, -3.0, 2.0, 20.0, -10.0, 15.0]), SOD)
    poses = depth_probe_poses(T, 30.0)
    assert np.allclose(poses[0], T) and np.allclose(poses[:, :3, :3], T[:3, :3])
    for p, d in ((poses[1], 30.0), (poses[2], -30.0)):
        assert p[2, 3] == pytest.approx(T[2, 3] + d)
        # the anatomy centre (X = c, camera point t) projects to the same pixel: t / t_z unchanged
        assert np.allclose(p[:2, 3] / p[2, 3], T[:2, 3] / T[2, 3])


def test_an_undetermined_depth_is_doubtful():
    s = VerdictSettings(min_depth_drop=0.02)
    v = judge(_evidence(depth_drop=0.005), s)
    assert v.label == "doubtful" and "depth is not determined" in v.reasons[0]
    assert judge(_evidence(depth_drop=0.05), s).label == "registered"


def test_verdict_rates_count_false_accepts_and_the_share_of_good_ones_accepted():
    rows = [{"mtre_mm": 2.0, "verdict": "registered"}, {"mtre_mm": 3.0, "verdict": "doubtful"},
            {"mtre_mm": 25.0, "verdict": "registered"}, {"mtre_mm": 40.0, "verdict": "failed"},
            {"mtre_mm": 1.0}]  # not judged: left out
    r = verdict_rates(rows, 10.0)
    assert r["within"] == 2 and r["off"] == 2 and r["accepted"] == pytest.approx(0.5) and r["false_accepts"] == 1
    assert r["verdicts"] == {"registered": 2, "doubtful": 1, "failed": 1}


def test_the_verdict_line_and_exit_statuses():
    v = Verdict("doubtful", ("a", "b"))
    assert v.line() == "verdict: doubtful (a; b)" and v.to_dict()["verdict_reasons"] == ["a", "b"]
    assert EXIT_STATUS == {"registered": 0, "doubtful": 3, "failed": 3}


def test_the_command_line_prints_the_last_line_and_exits_with_the_status(monkeypatch, capsys):
    """register's verdict reaches the exit status through sim.core.outputs.Written (main's plumbing)."""
    import register.commands as commands
    from register import cli
    from sim.core.outputs import Written

    monkeypatch.setattr(commands, "run_register",
                        lambda cmd: Written(["a.png"], last_line="verdict: doubtful (x)", exit_status=3))
    code = cli.main(["register", "--ct", "phantom", "--xray", "x.png", "--out", "o"])
    out = capsys.readouterr().out.strip().splitlines()
    assert code == 3 and out[-1] == "verdict: doubtful (x)" and out[-2] == "wrote a.png"


def _body_with_bones(bone_shift_px: int) -> np.ndarray:
    """A 128 px line-integral image: a body whose outline crosses the image (a step of 3, the
    strongest edge by far) over air, with anatomy inside it (smooth structure, sd 0.1, 4 px across),
    moved by ``bone_shift_px`` along the outline: the same outline, other anatomy."""
    from scipy import ndimage

    y, x = np.mgrid[0:128, 0:128].astype(float)
    body = 1.0 / (1.0 + np.exp(-(0.35 * x - y + 70.0)))  # the body above a sloping outline, air below
    texture = ndimage.gaussian_filter(np.random.default_rng(3).standard_normal((128, 128 + 64)), 4.0)
    texture = 0.1 * texture[:, 32 - bone_shift_px:160 - bone_shift_px] / texture.std()
    return body * (3.0 + texture)


def test_one_strong_edge_carrying_the_whole_similarity_is_doubtful_window_by_window():
    # truth: the DRR at a pose that puts the outline where the X-ray has it but the bones elsewhere
    # correlates with the X-ray as a whole (the outline dominates both images' gradients), window by
    # window it does not (the bones meet nothing); at the right pose both are 1
    xray = _body_with_bones(0)
    wrong, right = _body_with_bones(17), xray
    ev = {}
    for name, drr in (("wrong", wrong), ("right", right)):
        ev[name] = gather_evidence(similarity=0.93, pose=np.eye(4), image=xray, mask=None, drr=drr, toned=None,
                                   search=None, search_ran=False, network_pose=None, sod_mm=SOD, field_fraction=1.0)
    from register.engines.metrics import gradient_ncc
    assert gradient_ncc(xray, wrong)[0] > 0.85  # the whole image's similarity cannot tell
    assert ev["right"]["local_similarity"] == pytest.approx(1.0)
    s = VerdictSettings()
    assert ev["wrong"]["local_similarity"] < s.min_local_similarity
    v = judge({**ev["wrong"], "depth_drop": 0.3}, s)
    assert v.label == "doubtful" and any("window by window" in r for r in v.reasons)
    assert judge({**ev["right"], "depth_drop": 0.3}, s).label == "registered"
    assert judge({**ev["wrong"], "depth_drop": 0.3}, VerdictSettings(min_local_similarity=None)).label == "registered"


def test_a_field_smaller_than_one_window_leaves_the_local_similarity_unjudged():
    xray = _body_with_bones(0)
    mask = np.zeros(xray.shape, bool)
    mask[40:46, 40:46] = True  # 36 px: no 15 px window half inside
    ev = gather_evidence(similarity=0.93, pose=np.eye(4), image=xray, mask=mask, drr=xray, toned=None, search=None,
                         search_ran=False, network_pose=None, sod_mm=SOD, field_fraction=0.002)
    assert ev["local_similarity"] is None
    v = judge({**ev, "depth_drop": 0.3})
    assert v.label == "doubtful" and v.reasons == ("0 % of the X-ray used (< 10 %)",)  # judged by the field's share


def test_a_pose_found_by_local_similarity_is_judged_and_named_by_it_once():
    ev = _evidence(similarity=0.63, local_similarity=0.63, similarity_metric="local_gncc", depth_drop=0.2)
    v = judge(ev)
    assert v.label == "registered" and v.reasons[0] == "local similarity 0.63"
    assert sum("0.63" in r for r in v.reasons) == 1 and "searched again and judged by local similarity" in v.reasons
