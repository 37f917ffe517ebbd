"""The contextual iteration with an oracle predictor (the true label) converges to the truth."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from register.contextual import ContextualRegistration, ContextualSettings
from register.cmaes import RegistrationError


@pytest.fixture(scope="module")
def phantom():
    from sim.anatomy import anatomy_center
    from sim.phantom import make_pelvis_phantom

    vol = make_pelvis_phantom(0, spacing_mm=4.0)
    return vol, anatomy_center(vol)


def oracle(truth_T):
    """A predictor that knows the answer: g = -2 log_T(T_truth) for the pose of the DRR it gets."""
    from learn.labels import geodesic_label

    state = {}

    def predict(fixed, drr):
        return geodesic_label(torch.from_numpy(truth_T), torch.from_numpy(state["T"])).numpy()

    return predict, state


def test_oracle_iteration_reaches_the_truth_from_ap(phantom):
    from sim.geometry import pose_from_params
    from sim.se3 import rotation_error_deg, translation_error_mm

    vol, c = phantom
    truth = np.array([35.0, -15.0, 12.0, 60.0, -40.0, 50.0])
    reg = ContextualRegistration(vol, None, ContextualSettings(), size=(32, 32), center_lps=c)
    T_true = pose_from_params(truth, reg.geometry.sod_mm)
    predict, state = oracle(T_true)
    real_render = reg.renderer.render

    def render_and_remember(T):
        state["T"] = np.asarray(T).reshape(-1, 4, 4)[0]
        return real_render(T)

    reg.renderer.render = render_and_remember
    reg.predictor = predict
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
