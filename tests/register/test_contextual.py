"""The contextual iteration with an oracle predictor (the true label) converges to the truth."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from register.engines.contextual import ContextualRegistration, ContextualSettings
from register.engines.result import RegistrationError


@pytest.fixture(scope="module")
def phantom():
    from sim.ct.anatomy import anatomy_center
    from sim.ct.phantom import make_pelvis_phantom

    vol = make_pelvis_phantom(0, spacing_mm=4.0)
    return vol, anatomy_center(vol)


def oracle(truth_T):
    """A predictor that knows the answer: g = -2 log_T(T_truth) for the pose of the DRR it gets."""
    from learn.labels import geodesic_label

    state = {}

    def predict(fixed, drr):
        return geodesic_label(torch.from_numpy(truth_T), torch.from_numpy(state["T"])).numpy()

    return predict, state


def use_oracle(reg, truth_T) -> None:
    """Give ``reg`` the oracle predictor of ``truth_T``: its renderer remembers the pose it renders."""
    predict, state = oracle(truth_T)
    real_render = reg.renderer.render

    def render_and_remember(T):
        state["T"] = np.asarray(T).reshape(-1, 4, 4)[0]
        return real_render(T)

    reg.renderer.render = render_and_remember
    reg.predictor = predict


def test_oracle_iteration_reaches_the_truth_from_ap(phantom):
    from sim.projection.geometry import pose_from_params
    from sim.projection.se3 import rotation_error_deg, translation_error_mm

    vol, c = phantom
    truth = np.array([35.0, -15.0, 12.0, 60.0, -40.0, 50.0])
    reg = ContextualRegistration(vol, None, ContextualSettings(), size=(32, 32), center_lps=c)
    T_true = pose_from_params(truth, reg.geometry.sod_mm)
    use_oracle(reg, T_true)
    result = reg.register(np.zeros((32, 32)), np.zeros(6))
    # g = -2 log, so a step of 0.15 g removes 30 % of the remaining log (0.7^n); the stop
    # thresholds on the predicted step (0.05 deg, 0.2 mm) bound the final error by them / 0.3
    assert rotation_error_deg(result.pose, T_true) < 0.05 / 0.3
    assert translation_error_mm(result.pose, T_true) < 0.2 / 0.3
    n = len(result.history)
    # 0.3 * 0.7^n * 43 deg < 0.05 deg needs n >= 16; the translation (~100 mm) about 15
    assert 14 <= n <= 22, n
    rot_steps = [-h[1] for h in result.history]
    assert all(b < a for a, b in zip(rot_steps, rot_steps[1:]))  # predicted steps shrink monotonically


def test_bad_settings_are_named():
    # (the network predictor's checkpoint refusals: tests/learn/test_predict.py)
    with pytest.raises(RegistrationError, match="step must be in"):
        ContextualSettings(step=0.0)
    with pytest.raises(RegistrationError, match="max_iterations"):
        ContextualSettings(max_iterations=0)


def test_a_lost_network_pose_goes_through_the_global_search(phantom):
    """A network that points the wrong way ends far off; its narrow refinement cannot recover and
    stays lost. With the global search between the two, the grid supplies a start the refinement
    recovers from. A network that is right skips the grid."""
    from dataclasses import replace

    from register.engines.pipeline import NETWORK_DEPTH_RANGE_MM, REFINE_SETTINGS, ContextualPipeline
    from register.engines.search import GlobalSearchSettings, describe_search
    from sim.projection.geometry import pose_from_params
    from sim.projection.se3 import rotation_error_deg

    vol, c = phantom
    size = (64, 64)
    truth = np.array([18.0, -9.0, 6.0, 20.0, -12.0, 15.0])
    refine = replace(REFINE_SETTINGS, size=size, generations=(12,), polish_evals=60)
    search = GlobalSearchSettings(candidates=3)
    wrong = lambda fixed, drr: np.array([0.0, 0.0, 0.6, 0.0, 0.0, 0.0])  # noqa: E731: a steady 45 deg drift
    reg = ContextualPipeline(vol, wrong, ContextualSettings(max_iterations=10), size=size, center_lps=c,
                             refine=refine, search=search)
    fixed = reg.renderer.render(pose_from_params(truth, reg.geometry.sod_mm))[0]
    res = reg.register(fixed, np.zeros(6))
    assert "search_grid" in res.stage_seconds and any(h[0] == "search" for h in res.history)
    T_true = pose_from_params(truth, reg.geometry.sod_mm)
    assert rotation_error_deg(res.pose, T_true) < 2.0, res.params  # the search found it
    record = res.search
    assert len(record["refined"]) == len(record["finalists"]) >= 1
    assert record["chosen"] == int(np.argmax(record["refined"])) and res.similarity >= max(record["refined"])
    if len(record["refined"]) > 1:  # the finalists' CMA-ES without the polish, then the winner polished once
        assert [h[0] for h in res.history].count("polish") == 1 and res.history[-1][0] == "polish"
        assert not any(h[0].endswith(".polish") for h in res.history)
    # the refinement runs from each finalist: a wrong search winner (as at 1/4 resolution on realistic
    # frames) loses to the right runner-up once both are refined at full resolution
    far = truth + np.array([-25.0, 12.0, -10.0, -40.0, 30.0, -35.0])
    reg.search.register = lambda fixed, init, mask=None, poses=(), toned=None, before_grid=None: type(res)(
        params=far, pose=np.eye(4), projection=np.eye(3, 4), similarity=0.9, renders=0,
        stage_seconds={"search_local": 0.0}, search={**record, "finalists": [
            {"params": far.tolist(), "similarity": 0.9, "start": "grid"},
            {"params": (truth + [2.0, -2.0, 1.0, 5.0, -4.0, 8.0]).tolist(), "similarity": 0.5, "start": "grid"}]})
    chosen = reg.register(fixed, np.zeros(6))
    assert chosen.search["chosen"] == 1 and chosen.search["refined"][1] > chosen.search["refined"][0]
    assert rotation_error_deg(chosen.pose, T_true) < 1.0, chosen.params
    assert any(h[0].startswith("finalist1.") for h in chosen.history)
    assert [h[0] for h in chosen.history].count("polish") == 1 and chosen.history[-1][0] == "polish"
    assert "kept the second best (a grid pose" in describe_search(chosen.search)
    # without the search the same network stays lost
    no_search = ContextualPipeline(vol, wrong, ContextualSettings(max_iterations=10), size=size, center_lps=c,
                                   refine=refine)
    alone = no_search.register(fixed, np.zeros(6))
    assert rotation_error_deg(alone.pose, T_true) > 5.0 and alone.similarity < res.similarity
    # the refinement's depth box: wide around the network's own pose (no search), the translations'
    # after a search, whose starts' depths are searched; a depth box the caller set is kept
    assert no_search.refinement.settings.depth("range") == NETWORK_DEPTH_RANGE_MM == 90.0
    assert reg.refinement.settings.depth("range") == refine.range_mm == 30.0
    assert no_search.refinement.settings.depth("sigma") == reg.refinement.settings.depth("sigma") == 8.0
    kept = ContextualPipeline(vol, wrong, size=size, center_lps=c, refine=replace(refine, range_depth_mm=40.0))
    assert kept.refinement.settings.depth("range") == 40.0
    # a right network (the oracle): its pose is kept, no grid
    good = ContextualPipeline(vol, None, ContextualSettings(), size=size, center_lps=c, refine=refine,
                              search=search)
    use_oracle(good.contextual, T_true)
    found = good.register(fixed, np.zeros(6))
    assert "search_grid" not in found.stage_seconds and rotation_error_deg(found.pose, T_true) < 1.0
    with pytest.raises(RegistrationError, match="needs the refinement"):
        ContextualPipeline(vol, wrong, size=size, center_lps=c, refine=None, search=search)


@pytest.mark.parametrize("current_field", ["masked", "open"])
def test_the_network_sees_the_current_image_as_it_was_trained(phantom, current_field):
    # a predictor trained on masked current images gets the DRR filled outside the X-ray's field, one
    # trained on open ones (learn.online.CURRENT_FIELDS) the whole DRR; the X-ray is filled either way
    vol, c = phantom
    reg = ContextualRegistration(vol, None, ContextualSettings(max_iterations=1), size=(32, 32), center_lps=c)
    seen = []

    class Recorder:
        def __call__(self, fixed, drr):
            seen.append((fixed, drr))
            return np.zeros(6)

    rec = Recorder()
    rec.current_field = current_field
    reg.predictor = rec
    mask = np.zeros((32, 32), bool)
    mask[8:24, 8:24] = True
    fixed = np.random.default_rng(0).random((32, 32))
    reg.register(fixed, np.zeros(6), mask=mask)
    net_fixed, net_drr = seen[0]
    assert np.ptp(net_fixed[~mask]) == 0  # the X-ray is filled outside its field
    outside_varies = np.ptp(net_drr[~mask]) > 0
    assert outside_varies == (current_field == "open")
