"""The global pose search (register/engines/search.py): the FFT masked NCC against its definition, the grid's
in-plane shift against a known translation, and the search against a known pose of the phantom."""

from __future__ import annotations

import numpy as np
import pytest

from register.engines.result import RegistrationError
from register.engines.search import GlobalSearch, GlobalSearchSettings, describe_search, masked_ncc_shifts


@pytest.fixture(scope="module")
def phantom():
    from sim.ct.anatomy import anatomy_center
    from sim.ct.phantom import make_pelvis_phantom

    vol = make_pelvis_phantom(0, spacing_mm=4.0)
    return vol, anatomy_center(vol)


def test_masked_ncc_shifts_equals_the_direct_sum():
    # the FFT route against the NCC written out per shift: equal to single-precision rounding (the FFTs run
    # in float32, about 1e-7 relative; 1e-5 allows the sums' cancellation in the variances)
    rng = np.random.default_rng(0)
    t = rng.normal(size=(7, 9))
    m = rng.random((7, 9)) > 0.3
    imgs = rng.normal(size=(3, 12, 13))
    out = masked_ncc_shifts(t, m, imgs)
    assert out.shape == (3, 6, 5)
    for b in range(3):
        for u in range(6):
            for v in range(5):
                a, w = t[m], imgs[b, u:u + 7, v:v + 9][m]
                ref = np.sum((a - a.mean()) * (w - w.mean())) / np.sqrt(np.sum((a - a.mean()) ** 2) * np.sum((w - w.mean()) ** 2))
                assert out[b, u, v] == pytest.approx(ref, abs=1e-5)
    # the template cut out of an image is found at its place with NCC 1, whatever the gain and offset
    img = rng.normal(size=(1, 20, 20))
    hit = masked_ncc_shifts(3.0 * img[0, 5:12, 8:17] + 2.0, m, img)[0]
    assert np.unravel_index(hit.argmax(), hit.shape) == (5, 8) and hit.max() == pytest.approx(1.0, abs=1e-5)
    # several templates with one mask: each the single template's result (shared terms computed once)
    t2 = t ** 3
    both = masked_ncc_shifts(np.stack([t, t2]), m, imgs)
    assert both.shape == (2, 3, 6, 5)
    np.testing.assert_allclose(both[0], out, atol=1e-12)
    np.testing.assert_allclose(both[1], masked_ncc_shifts(t2, m, imgs), atol=1e-12)
    # constant images under the mask score 0, not NaN
    assert np.all(masked_ncc_shifts(t, m, np.ones((1, 12, 13))) == 0.0)
    with pytest.raises(RegistrationError, match="masked_ncc_shifts"):
        masked_ncc_shifts(t, m, imgs[:, :5])


def test_settings_are_checked():
    offsets = GlobalSearchSettings().grid_offsets()
    assert len(offsets) == 11 * 6 * 6 * 5  # +-40 / 8 deg, +-20 / 8 deg twice (no 0), 5 depths
    assert np.allclose(offsets.mean(0), 0) and np.allclose(np.abs(offsets).max(0), [40, 20, 20, 0, 0, 75])
    for bad, match in [(dict(step_deg=0.0), "step_deg"), (dict(range_deg=(40, 20)), "range_deg"),
                       (dict(candidates=0), "candidates"), (dict(depths=1.5), "depths"),
                       (dict(found_above=2.0), "found_above"), (dict(refined_above=0.8), "refined_above"),
                       (dict(factor=True), "factor"),
                       (dict(rescore=-1), "rescore"), (dict(local_factor=0), "local_factor"),
                       (dict(finalists=0), "finalists"), (dict(local_generations=0), "local_generations"),
                       (dict(local_fine_generations=-1), "local_fine_generations"),
                       (dict(local_range_depth_mm=0.0), "local_range_depth_mm"),
                       (dict(local_sigma_depth_mm=float("nan")), "local_sigma_depth_mm"),
                       (dict(metric="mutual_information"), "metric: .*unknown name 'mutual_information'")]:
        with pytest.raises(RegistrationError, match=match):
            GlobalSearchSettings(**bad)


def test_the_grid_finds_the_in_plane_translation_of_a_grid_rotation(phantom):
    """A pose on the grid's rotations and depths with an arbitrary in-plane translation: the best grid
    pose is that rotation and depth, its translation within one search pixel (at the anatomy's depth)."""
    from sim.projection.geometry import pose_from_params

    vol, c = phantom
    s = GlobalSearchSettings(range_deg=(20.0, 10.0, 10.0), step_deg=10.0, depths=3, range_mm=40.0)
    search = GlobalSearch(vol, s, size=(128, 128), center_lps=c)
    truth = np.array([10.0, -10.0, 0.0, 17.0, -11.0, 40.0])
    fixed = search.local.render(truth, 1)[0]
    params, scores = search.grid(fixed, np.zeros(6))
    g = search.level_geometry
    mm_per_px = (g.sod_mm + truth[5]) * g.pixel_spacing_mm / g.sdd_mm
    assert np.allclose(params[0][[0, 1, 2, 5]], truth[[0, 1, 2, 5]]), params[0]
    assert np.all(np.abs(params[0][3:5] - truth[3:5]) <= mm_per_px), (params[0], mm_per_px)
    # whole-pixel shifts: up to half a search pixel off, which costs the gradient NCC about 0.1
    assert scores[0] > 0.8 and scores[0] >= scores[1:].max()
    # the rescoring at 1/2 resolution keeps the truth's grid pose first and halves the shift's error
    top, top_scores = search.rescored(fixed, params[:8])
    g2 = search.rescore_geometry
    assert g2.height == 2 * g.height and np.allclose(top[0][[0, 1, 2, 5]], truth[[0, 1, 2, 5]])
    assert np.all(np.abs(top[0][3:5] - truth[3:5]) <= mm_per_px / 2), (top[0], mm_per_px / 2)
    assert top_scores[0] >= top_scores[1:].max() and top_scores[0] > scores[0]  # sharper: closer to 1
    # each pose's score is its own: scored alone, a grid pose scores what it scored beside its neighbours
    # (a Sobel over the whole batch also smoothed along it, blending each DRR with the next pose's)
    batch = np.sort(search.rescored(fixed, params[1:4])[1])
    alone = np.sort([search.rescored(fixed, params[k:k + 1])[1][0] for k in range(1, 4)])
    np.testing.assert_allclose(alone, batch, atol=1e-6)
    # a field: only its pixels count, and the shift is still found
    field = np.zeros((128, 128), bool)
    field[16:112, 24:104] = True
    params, _ = search.grid(np.where(field, fixed, 0.0), np.zeros(6), mask=field)
    assert np.all(np.abs(params[0][3:5] - truth[3:5]) <= mm_per_px)
    with pytest.raises(RegistrationError, match="too few"):
        search.grid(fixed, np.zeros(6), mask=np.eye(128, dtype=bool))
    # several versions of the X-ray, one rendering: each ranking is the one grid() gives it alone
    curved = np.where(field, fixed, 0.0) ** 2.0
    both = search.grids([np.where(field, fixed, 0.0), curved], np.zeros(6), mask=field)
    for (p_both, s_both), image in zip(both, (np.where(field, fixed, 0.0), curved)):
        p_one, s_one = search.grid(image, np.zeros(6), mask=field)
        np.testing.assert_allclose(p_both, p_one, atol=1e-9)
        np.testing.assert_allclose(s_both, s_one, atol=1e-12)
    assert not np.allclose(both[0][1], both[1][1])  # the curve changes the scores: the test can fail
    assert pose_from_params(params[0], g.sod_mm).shape == (4, 4)


def test_the_local_searches_take_the_depth_box_given(phantom):
    """``local_range_depth_mm`` / ``local_sigma_depth_mm`` reach both local CMA-ES engines (the
    refinement's own depth box: register.engines.pipeline.REFINE_SETTINGS); unset, depth keeps the
    translations' box and step."""
    vol, c = phantom
    deep = GlobalSearch(vol, GlobalSearchSettings(local_range_depth_mm=90.0, local_sigma_depth_mm=12.0), size=(64, 64),
                        center_lps=c)
    plain = GlobalSearch(vol, GlobalSearchSettings(), size=(64, 64), center_lps=c)
    for engine in (deep.local, deep.local_fine):
        assert engine.settings.depth("range") == 90.0 and engine.settings.depth("sigma") == 12.0
        assert engine.settings.range_mm == 35.0
    for engine in (plain.local, plain.local_fine):
        assert engine.settings.depth("range") == 35.0 and engine.settings.depth("sigma") == 8.0


def test_the_search_finds_a_far_pose_and_skips_the_grid_for_a_good_one(phantom):
    from sim.projection.geometry import pose_from_params
    from sim.projection.se3 import rotation_error_deg

    vol, c = phantom
    search = GlobalSearch(vol, GlobalSearchSettings(candidates=3), size=(64, 64), center_lps=c)
    truth = np.array([27.0, 8.0, -6.0, 35.0, -20.0, 25.0])  # off the grid, far from AP
    fixed = search.local.render(truth, 1)[0]
    T = pose_from_params(truth, search.level_geometry.sod_mm)
    wrong = np.array([-30.0, 0.0, 0.0, -40.0, 0.0, 0.0])  # a lost network's pose
    res = search.register(fixed, np.zeros(6), poses=[wrong])
    assert "search_grid" in res.stage_seconds and len(res.history) == 4  # the given pose, then 3 candidates
    n_grid = len(search.settings.grid_offsets())
    assert res.search["grid_render_s"] > 0 and res.search["grid_ncc_s"] > 0
    assert res.search["grid_render_s"] + res.search["grid_ncc_s"] <= res.stage_seconds["search_grid"]
    finalists = res.search["finalists"]
    assert {k: v for k, v in res.search.items() if not k.endswith("_s") and k != "finalists"} == {
        "given_similarity": res.history[0][1], "given_score": res.history[0][1], "given_clipped": False,
        "found_above": 0.85, "always_grid": False, "local": False, "grid_poses": n_grid, "candidates": 3, "start": "grid",
        "similarity": res.similarity}  # a line DRR: the skip's score (plain gradient NCC) is the local similarity
    # finalists: the result first, then the next best local results, each apart from those before it
    assert 1 <= len(finalists) <= 3 and finalists[0]["params"] == res.params.tolist()
    sims = [f["similarity"] for f in finalists]
    assert sims == sorted(sims, reverse=True) and sims[0] == res.similarity
    assert set(sims) <= {h[1] for h in res.history}
    for i, f in enumerate(finalists):
        for g in finalists[:i]:
            d = np.abs(np.subtract(f["params"], g["params"]))
            assert np.any(d[:3] > 2.0) or np.any(d[3:] > 10.0)
    local_results = sorted((h[1] for h in res.history), reverse=True)
    if len(finalists) < 3:  # fewer only when the other local results ended near a finalist
        assert len(set(np.round(local_results, 12))) >= len(finalists)
    assert f"{n_grid} grid poses, 3 searched locally; refined from a grid pose" in describe_search(res.search)
    assert rotation_error_deg(res.pose, T) < 3.0 and np.linalg.norm(res.params[3:5] - truth[3:5]) < 8.0, res.params
    good = search.register(fixed, np.zeros(6), poses=[truth + [2.0, -1.0, 1.0, 4.0, -3.0, 5.0]])
    assert "search_grid" not in good.stage_seconds and good.similarity >= search.settings.found_above
    assert rotation_error_deg(good.pose, T) < 3.0
    assert good.search["grid_poses"] == 0 and good.search["start"] == "given"
    assert good.search["finalists"] == [{"params": good.params.tolist(), "similarity": good.similarity,
                                         "start": "given"}]  # the grid skipped: the network's pose only
    assert "grid skipped" in describe_search(good.search)
    # a network pose far outside the prior box is clipped into it before its local search
    lost = search.register(fixed, np.zeros(6), poses=[np.array([5.0, 0.0, 0.0, 0.0, 0.0, -500.0])])
    assert lost.search["given_clipped"] and good.search["given_clipped"] is False
    s = search.settings
    given_row = np.array(lost.history[0][2])
    assert given_row[5] >= -s.range_mm - s.local_range_mm - 1e-9, given_row  # the local box around -75 mm
    assert rotation_error_deg(lost.pose, T) < 3.0
    # a toned version of the X-ray (here a gamma curve of it): the grid ranks both, the starts split
    # between the rankings (still 3), and the pose is found
    toned = search.register(fixed, np.zeros(6), poses=[wrong], toned=(fixed / fixed.max()) ** 2.5)
    assert toned.search["candidates"] == 3 and toned.search["grid_poses"] == n_grid
    assert rotation_error_deg(toned.pose, T) < 3.0
    # the local searches score a display image (one with a toned version) tone-tolerantly and an
    # image of line integrals plainly: the given pose's local search is either engine's, run alone
    assert search.settings.metric == "tone_tolerant_gncc"
    for run, metric in ((res, "gncc"), (toned, "tone_tolerant_gncc")):
        alone = search.local.scored_by((metric,)).register_many(fixed, [wrong])[0]
        assert run.history[0][1] == pytest.approx(alone.similarity, abs=1e-12), metric
    assert res.history[0][1] != pytest.approx(toned.history[0][1], abs=1e-6)  # the two metrics differ here
    with pytest.raises(RegistrationError, match="toned: expected the X-ray's shape"):
        search.register(fixed, np.zeros(6), toned=np.zeros((8, 8)))
    with pytest.raises(RegistrationError, match="divisible"):
        GlobalSearch(vol, size=(30, 30), center_lps=c)


def test_only_contextual_cmaes_takes_the_search(phantom):
    from register.engines.methods import build_method

    vol, c = phantom
    for method in ("cmaes", "contextual"):
        with pytest.raises(RegistrationError, match="global search is part of contextual\\+cmaes"):
            build_method(method, vol, center_lps=c, size=(32, 32), search=GlobalSearchSettings(),
                         model=None if method == "cmaes" else (lambda f, d: np.zeros(6)))
