"""CMA-ES registration recovers known poses; the evaluation's error measures are exact."""

from __future__ import annotations

import numpy as np
import pytest

from register.engines.cmaes import CMAESRegistration, CMAESSettings
from register.engines.result import RegistrationError
from register.evaluation.errors import pose_errors
from register.evaluation.evaluate import EvaluationError, EvaluationSettings, sample_cases, summarize
from sim.projection.geometry import pose_from_params, projection_matrix
from sim.projection.drr import DRRRenderer, RenderSettings

SMALL = CMAESSettings(levels=(2, 1), size=(64, 64), popsize=12, generations=(25, 15), polish_evals=120)


@pytest.fixture(scope="module")
def phantom():
    from sim.ct.anatomy import anatomy_center
    from sim.ct.phantom import make_pelvis_phantom

    vol = make_pelvis_phantom(0, spacing_mm=4.0)
    return vol, anatomy_center(vol)


def test_recovers_a_known_small_offset_on_the_phantom(phantom):
    vol, c = phantom
    truth = np.array([6.0, -4.0, 3.0, 8.0, -6.0, 15.0])
    target = DRRRenderer(vol, RenderSettings(size=(64, 64)), center_lps=c).render_params(truth)[0]
    engine = CMAESRegistration(vol, SMALL, center_lps=c)
    start = truth + np.array([3.0, -3.0, 2.0, 5.0, 5.0, -10.0])
    result = engine.register(target, start)
    T = pose_from_params(truth, engine.geometry.sod_mm)
    from sim.projection.se3 import rotation_error_deg, translation_error_mm

    # same renderer for target and DRRs: the optimum is the truth; 0.5 deg / 2 mm leaves room for
    # the optimiser's tolerances at 64 x 64 pixels of 4.6 mm (3.2 mm at the isocentre)
    assert rotation_error_deg(result.pose, T) < 0.5
    assert translation_error_mm(result.pose, T) < 2.0
    assert result.similarity > 0.99
    assert result.renders > SMALL.popsize * 10 and set(result.stage_seconds) == {"level0", "level1", "polish"}
    np.testing.assert_allclose(result.projection, projection_matrix(engine.geometry, result.pose, c), atol=1e-9)


def test_similarity_history_never_gets_worse_within_a_level(phantom):
    vol, c = phantom
    truth = np.array([4.0, 2.0, -2.0, 0.0, 5.0, 0.0])
    target = DRRRenderer(vol, RenderSettings(size=(64, 64)), center_lps=c).render_params(truth)[0]
    result = CMAESRegistration(vol, SMALL, center_lps=c).register(target, np.zeros(6))
    for level in ("level0", "level1"):
        best = [h[1] for h in result.history if h[0] == level]
        assert np.all(np.diff(best) >= -1e-12)


def test_restarts_run_only_while_lost_and_keep_the_best_similarity(phantom):
    vol, c = phantom
    truth = np.array([4.0, 2.0, -2.0, 0.0, 5.0, 0.0])
    target = DRRRenderer(vol, RenderSettings(size=(64, 64)), center_lps=c).render_params(truth)[0]
    tiny = CMAESSettings(levels=(1,), size=(64, 64), popsize=6, generations=(4,), metrics=("gncc",), polish=False)
    first = CMAESRegistration(vol, tiny, center_lps=c).register(target, np.zeros(6))
    # a bar no search can reach: every restart runs (new seed, twice the population each time);
    # one full-resolution level, so the history's best is the final similarity
    from dataclasses import replace

    lost = CMAESRegistration(vol, replace(tiny, restarts=2, restart_below=1.0), center_lps=c).register(
        target, np.zeros(6))
    assert set(lost.stage_seconds) == {"level0", "restart1.level0", "restart2.level0"}
    finals = [lost.history[i][1] for i, h in enumerate(lost.history)
              if i + 1 == len(lost.history) or lost.history[i + 1][0] != h[0]]
    assert lost.similarity >= first.similarity - 1e-9 and lost.similarity == pytest.approx(max(finals), abs=1e-6)
    assert lost.renders > 3 * first.renders  # 6 + 12 + 24 per generation
    # a bar the first search clears: no restart, the same result as without restarts
    found = CMAESRegistration(vol, replace(tiny, restarts=2, restart_below=-1.0), center_lps=c).register(
        target, np.zeros(6))
    assert set(found.stage_seconds) == {"level0"}
    np.testing.assert_array_equal(found.params, first.params)


def test_along_the_view_ray_the_centre_keeps_its_pixel_and_the_depth_moves(phantom):
    from register.engines.cmaes import along_view_ray

    vol, c = phantom
    engine = CMAESRegistration(vol, SMALL, center_lps=c)
    sod = engine.geometry.sod_mm
    p = np.array([12.0, -7.0, 5.0, 30.0, -22.0, 18.0])
    moved = along_view_ray(p, [-40.0, 0.0, 25.0], sod)
    np.testing.assert_array_equal(moved[:, :3], np.repeat(p[None, :3], 3, 0))  # the rotation stays
    np.testing.assert_allclose(moved[1], p, atol=1e-12)
    np.testing.assert_allclose(moved[:, 5] - p[5], [-40.0, 0.0, 25.0], atol=1e-9)
    # the anatomy centre projects to the same pixel (closed form: x / z at fixed ratio)
    px = []
    for q in moved:
        P = projection_matrix(engine.geometry, pose_from_params(q, sod), c)
        h = P @ np.append(c, 1.0)
        px.append(h[:2] / h[2])
    np.testing.assert_allclose(px, np.repeat(px[1][None], 3, 0), atol=1e-9)
    # and any other point does not (the magnification changes)
    off = c + np.array([60.0, 0.0, 0.0])
    a, b = (projection_matrix(engine.geometry, pose_from_params(q, sod), c) @ np.append(off, 1.0) for q in moved[:2])
    assert abs(a[0] / a[2] - b[0] / b[2]) > 0.5
    with pytest.raises(RegistrationError, match="in front of the source"):
        along_view_ray(np.array([0, 0, 0, 0, 0, -sod - 1.0]), [0.0], sod)


def test_the_polish_recovers_a_depth_error_along_the_view_ray(phantom):
    """A start 24 mm off along the view ray (the centre's projection right, the magnification
    wrong) and a CMA-ES that barely moves: the polish, whose first directions include the view
    ray, lands on the truth's depth; without the polish the depth error stays."""
    from dataclasses import replace

    from register.engines.cmaes import along_view_ray

    vol, c = phantom
    truth = np.array([6.0, -4.0, 3.0, 25.0, -15.0, 10.0])
    still = CMAESSettings(levels=(1,), size=(64, 64), popsize=4, generations=(1,), sigma_deg=0.01, sigma_mm=0.01,
                          metrics=("gncc",), polish=False)
    engine = CMAESRegistration(vol, replace(still, polish=True, polish_evals=300), center_lps=c)
    sod = engine.geometry.sod_mm
    target = engine.render(truth, 1)[0]
    start = along_view_ray(truth, [24.0], sod)[0]
    polished = engine.register(target, start)
    assert abs(polished.params[5] - truth[5]) <= 2.0, polished.params
    plain = CMAESRegistration(vol, still, center_lps=c).register(target, start)
    assert abs(plain.params[5] - truth[5]) > 20.0 and plain.similarity < polished.similarity


def test_the_pattern_polish_reaches_the_truth_from_a_small_offset_in_fewer_renders(phantom):
    """From 1 deg / 2 mm off a DRR target (CMA-ES held still), both polishes land within 0.2 deg and
    1 mm of the truth; the pattern polish, batched, uses fewer evaluations than its budget; an
    unknown method is refused."""
    from dataclasses import replace

    vol, c = phantom
    truth = np.array([5.0, -3.0, 2.0, 10.0, -6.0, 4.0])
    still = CMAESSettings(levels=(1,), size=(64, 64), popsize=4, generations=(1,), sigma_deg=0.01, sigma_mm=0.01,
                          metrics=("gncc",), polish=True, polish_evals=300)
    start = truth + np.array([1.0, -1.0, 0.5, 2.0, -1.5, 2.0])
    results = {}
    for method in ("powell", "pattern"):
        engine = CMAESRegistration(vol, replace(still, polish_method=method), center_lps=c)
        target = engine.render(truth, 1)[0]
        results[method] = engine.register(target, start)
        err = np.abs(results[method].params - truth)
        assert err[:3].max() < 0.2 and err[3:].max() < 1.0, (method, results[method].params)
    assert results["pattern"].renders < 250
    with pytest.raises(RegistrationError, match="polish_method"):
        replace(still, polish_method="newton")


def test_the_depth_gets_its_own_box_and_step(phantom):
    """A start 50 mm off in depth alone (what the network's pose often is: docs/results.md): a box of
    +-30 mm in every translation leaves the search on its edge, 20 mm from the truth; the depth's own
    box (``range_depth_mm``, the refinement's) reaches the truth, with the translations' first step
    or a longer one of its own (``sigma_depth_mm``). The other translations keep ``range_mm``."""
    from dataclasses import replace

    vol, c = phantom
    truth = np.array([4.0, -3.0, 2.0, 6.0, -4.0, 5.0])
    narrow = CMAESSettings(levels=(1,), size=(64, 64), popsize=24, generations=(40,), sigma_deg=3.0, sigma_mm=8.0,
                           range_deg=10.0, range_mm=30.0, metrics=("gncc",), polish=False)
    engine = CMAESRegistration(vol, narrow, center_lps=c)
    target = engine.render(truth, 1)[0]
    start = truth + np.array([0.0, 0.0, 0.0, 0.0, 0.0, 50.0])
    boxed = engine.register(target, start)
    assert boxed.params[5] == pytest.approx(start[5] - 30.0, abs=1.0), boxed.params  # on the box's edge
    for sigma_depth in (None, 24.0):
        deep = CMAESRegistration(vol, replace(narrow, sigma_depth_mm=sigma_depth, range_depth_mm=90.0), center_lps=c)
        found = deep.register(target, start)
        assert abs(found.params[5] - truth[5]) < 3.0 and found.similarity > boxed.similarity, (sigma_depth,
                                                                                               found.params)
        lo, hi = deep._box(start)
        np.testing.assert_allclose(hi - start, [10.0] * 3 + [30.0, 30.0, 90.0])
        np.testing.assert_allclose(deep._scale()[3:], [8.0 / 3.0] * 2 + [(sigma_depth or 8.0) / 3.0])
    assert narrow.depth("range") == 30.0 and narrow.depth("sigma") == 8.0


def test_searches_in_lockstep_give_each_start_its_own_result(phantom):
    """register_many renders every search's population in one batch; each search draws from its own
    generator, so each start gets exactly the result register gives it alone."""
    vol, c = phantom
    engine = CMAESRegistration(vol, CMAESSettings(levels=(2, 1), size=(64, 64), popsize=8, generations=(8, 4),
                                                  polish_evals=40), center_lps=c)
    target = engine.render(np.array([6.0, -4.0, 3.0, 8.0, -6.0, 15.0]), 1)[0]
    starts = np.array([[9.0, -7.0, 5.0, 13.0, -1.0, 5.0], [0.0] * 6, [3.0, 3.0, -3.0, 20.0, -20.0, -20.0]])
    many = engine.register_many(target, starts)
    for start, got in zip(starts, many):
        alone = engine.register(target, start)
        np.testing.assert_array_equal(got.params, alone.params)
        assert got.similarity == alone.similarity and got.renders == alone.renders
        assert [h[0] for h in got.history] == [h[0] for h in alone.history]
    assert len({tuple(r.params) for r in many}) == 3  # three searches, not one repeated
    unpolished = engine.register_many(target, starts[:1], polish=False)[0]
    assert "polish" not in unpolished.stage_seconds and unpolished.history[-1][0] == "level1"
    finished = engine.polish(target, unpolished.params, start=starts[0])
    assert finished.similarity >= unpolished.similarity and set(finished.stage_seconds) == {"polish"}
    assert engine.register_many(target, np.zeros((0, 6))) == []
    with pytest.raises(RegistrationError, match="empty"):
        engine.register_many(target, np.array([[0.0, 0.0, 0.0, 3000.0, 0.0, 0.0]]))


def test_scored_by_changes_the_similarity_and_shares_the_renderers(phantom):
    vol, c = phantom
    reg = CMAESRegistration(vol, CMAESSettings(size=(32, 32), levels=(2,), generations=(3,),
                                               metrics=("tone_tolerant_gncc",), polish=False), center_lps=c)
    plain = reg.scored_by(("gncc",))
    assert plain.settings.metrics == ("gncc",) and reg.settings.metrics == ("tone_tolerant_gncc",)
    assert plain.renderers is reg.renderers and reg.scored_by(("tone_tolerant_gncc",)) is reg
    fixed = reg.render(np.array([3.0, 0.0, 0.0, 5.0, 0.0, 0.0]))[0]
    a, b = reg.register(fixed), plain.register(fixed)
    assert a.similarity != pytest.approx(b.similarity, abs=1e-9)  # each scored by its own metric
    with pytest.raises(RegistrationError, match="metric"):
        reg.scored_by(("no_such_metric",))


def test_bad_settings_and_inputs_are_named(phantom):
    with pytest.raises(RegistrationError, match="restarts"):
        CMAESSettings(restarts=-1)
    with pytest.raises(RegistrationError, match="restart_below"):
        CMAESSettings(restart_below=float("nan"))
    with pytest.raises(RegistrationError, match="divisible"):
        CMAESSettings(levels=(3,), size=(64, 64))
    with pytest.raises(RegistrationError, match="popsize"):
        CMAESSettings(popsize=2)
    for bad_depth in (0.0, -5.0, float("nan"), "30", True):
        with pytest.raises(RegistrationError, match="range_depth_mm"):
            CMAESSettings(range_depth_mm=bad_depth)
    with pytest.raises(RegistrationError, match="sigma_depth_mm"):
        CMAESSettings(sigma_depth_mm=float("inf"))
    assert CMAESSettings(range_depth_mm=np.int64(90), sigma_mm=np.float32(8.0)).depth("range") == 90.0  # numpy numbers
    with pytest.raises(RegistrationError, match="one per level"):
        CMAESSettings(levels=(4, 2, 1), generations=(10, 10))
    vol, c = phantom
    engine = CMAESRegistration(vol, SMALL, center_lps=c)
    with pytest.raises(RegistrationError, match=r"\(64, 64\)"):
        engine.register(np.zeros((32, 32)))
    bad = np.zeros((64, 64))
    bad[3, 3] = np.nan
    with pytest.raises(RegistrationError, match="NaN"):
        engine.register(bad)


def test_pose_errors_against_hand_computed_values():
    from sim.projection.scene import load_scene

    g = load_scene("cios_fusion").geometry_at(128, 128)
    c = np.array([1.0, -2.0, 3.0])
    T_true = pose_from_params(np.array([10.0, 5.0, -3.0, 2.0, 1.0, 0.0]), g.sod_mm)
    # a pure translation of the volume by d (camera frame): every point moves by |d|
    d = np.array([3.0, 4.0, 0.0])
    T_est = T_true.copy()
    T_est[:3, 3] += d
    pts = c + np.random.default_rng(0).normal(scale=50, size=(100, 3))
    err = pose_errors(T_est, T_true, pts, c, projection_matrix(g, T_est, c), projection_matrix(g, T_true, c),
                      g.pixel_spacing_mm)
    assert err["rot_err_deg"] == pytest.approx(0.0, abs=1e-9)
    assert err["trans_err_mm"] == pytest.approx(5.0)
    assert err["depth_err_mm"] == pytest.approx(0.0, abs=1e-12)  # across the beam only
    assert err["mtre_mm"] == pytest.approx(5.0)
    # a lateral shift of 5 mm at depth z projects to 5 * SDD / z mm on the detector
    z = (pts - c) @ T_true[2, :3] + T_true[2, 3]
    assert err["mpd_mm"] == pytest.approx(np.mean(5.0 * g.sdd_mm / z), rel=1e-6)
    # a rotation by 2 degrees about the anatomy centre: rotation error 2, translation error 0
    from sim.projection.se3 import so3_exp

    T_rot = T_true.copy()
    T_rot[:3, :3] = T_true[:3, :3] @ so3_exp(np.array([0.0, 0.0, np.radians(2.0)]))
    err = pose_errors(T_rot, T_true, pts, c, projection_matrix(g, T_rot, c), projection_matrix(g, T_true, c),
                      g.pixel_spacing_mm)
    assert err["rot_err_deg"] == pytest.approx(2.0, rel=1e-9)
    assert err["trans_err_mm"] == pytest.approx(0.0, abs=1e-9)
    # the centre moved along the camera's axis by 7 mm and 1 mm across it: depth 7 of sqrt(50)
    T_deep = T_true.copy()
    T_deep[:3, 3] += np.array([0.0, 1.0, -7.0])
    err = pose_errors(T_deep, T_true, pts, c, projection_matrix(g, T_deep, c), projection_matrix(g, T_true, c),
                      g.pixel_spacing_mm)
    assert err["depth_err_mm"] == pytest.approx(7.0) and err["trans_err_mm"] == pytest.approx(np.sqrt(50.0))


def test_cases_are_seeded_and_local_starts_stay_within_their_limits():
    t1, s1 = sample_cases(EvaluationSettings(cases=50, seed=3, start="local"))
    t2, s2 = sample_cases(EvaluationSettings(cases=50, seed=3, start="local"))
    np.testing.assert_array_equal(t1, t2)
    np.testing.assert_array_equal(s1, s2)
    d = s1 - t1
    assert np.all(np.linalg.norm(d[:, :3], axis=1) <= 5.0 / np.sqrt(3) + 1e-9)
    assert np.all(np.linalg.norm(d[:, 3:], axis=1) <= 10.0 + 1e-9)
    _, s_ap = sample_cases(EvaluationSettings(cases=5, start="ap"))
    assert not s_ap.any()
    assert np.all(np.abs(t1[:, 0]) <= 40) and np.all(np.abs(t1[:, 3:]) <= 75)
    with pytest.raises(EvaluationError, match="start"):
        EvaluationSettings(start="far")


def test_summary_statistics():
    rows = [{"method": "m", "rot_err_deg": v, "trans_err_mm": 2 * v, "mtre_mm": 12 * v, "mpd_mm": v,
             "time_s": 1.0, "success": v < 0.5} for v in (0.1, 0.2, 0.9, 2.0)]
    s = summarize(rows, EvaluationSettings())["m"]
    assert s["rot_err_deg"]["mean"] == pytest.approx(0.8)
    assert s["rot_err_deg"]["median"] == pytest.approx(0.55)
    assert s["rot_err_deg"]["std"] == pytest.approx(np.std([0.1, 0.2, 0.9, 2.0], ddof=1))
    assert s["success_mtre"] == pytest.approx(0.5)  # mTRE 1.2, 2.4 < 10 mm; 10.8, 24 not
    assert s["success_rot"] == pytest.approx(0.75)


def test_a_ct_outside_the_view_is_refused(phantom):
    vol, c = phantom
    engine = CMAESRegistration(vol, SMALL, center_lps=c)
    with pytest.raises(RegistrationError, match="does not overlap the view"):
        engine.register(np.ones((64, 64)), np.array([0, 0, 0, 600.0, 0, 0]))
