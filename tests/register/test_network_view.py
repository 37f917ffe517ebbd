"""A network framed by the detector (train.framing = "detector") sees the X-ray's whole detector at
its own size, the field masked, and DRRs rendered for that detector, while CMA-ES keeps the crop."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from register.engines.contextual import ContextualRegistration, ContextualSettings
from register.xray.network_view import NetworkView, network_view


@pytest.fixture(scope="module")
def phantom():
    from sim.anatomy import anatomy_center
    from sim.phantom import make_pelvis_phantom

    vol = make_pelvis_phantom(0, spacing_mm=4.0)
    return vol, anatomy_center(vol)


class _Oracle:
    """The true label for the pose last rendered by the renderer it watches; records the image shapes."""

    def __init__(self, truth_T, framing):
        self.truth_T, self.framing, self.size, self.shapes, self.T = truth_T, framing, (32, 32), [], None

    def watch(self, renderer):
        real = renderer.render

        def render(T):
            self.T = np.asarray(T).reshape(-1, 4, 4)[0]
            return real(T)

        renderer.render = render

    def __call__(self, fixed, drr):
        from learn.labels import geodesic_label

        self.shapes.append((fixed.shape, drr.shape))
        return geodesic_label(torch.from_numpy(self.truth_T), torch.from_numpy(self.T)).numpy()


def test_a_detector_framed_network_sees_the_whole_detector_and_converges(phantom):
    from sim.geometry import pose_from_params
    from sim.scene import load_scene
    from sim.se3 import rotation_error_deg

    vol, c = phantom
    full = load_scene("cios_fusion").geometry_at(32, 32)
    crop = full.resized(16, 16)  # stands in for the X-ray cropped to its field (another detector)
    truth = np.array([20.0, -10.0, 5.0, 30.0, -20.0, 25.0])
    T_true = pose_from_params(truth, full.sod_mm)
    oracle = _Oracle(T_true, "detector")
    reg = ContextualRegistration(vol, oracle, ContextualSettings(), size=(16, 16), geometry=crop, center_lps=c)
    view = NetworkView(np.zeros((32, 32)), np.ones((32, 32), bool), full)
    oracle.watch(reg._view_renderer(full))
    result = reg.register(np.zeros((16, 16)), np.zeros(6), network_view=view)
    assert oracle.shapes and all(s == ((32, 32), (32, 32)) for s in oracle.shapes)
    assert rotation_error_deg(result.pose, T_true) < 0.2
    assert len(reg._view_renderers) == 1  # made once per view geometry


def test_network_view_follows_the_predictors_framing(phantom, tmp_path):
    """``network_view`` fits the prepared X-ray's whole detector (and its field) into the network's
    size for a detector-framed predictor, and is None for a field-framed one."""
    from register.xray.prepare import prepare_xray
    from sim.geometry import pose_from_params
    from sim.physics.display import Collimator
    from sim.drr import DRRRenderer, RenderSettings

    vol, c = phantom
    r = DRRRenderer(vol, RenderSettings(size=(96, 96)), center_lps=c)
    img = r.render(pose_from_params(np.zeros((1, 6)), r.geometry.sod_mm))[0]
    col = Collimator(shape="circle", radius=0.3, center=(0.45, 0.5))
    shown = np.where(col.mask(96, 96), img, 0.0)
    path = tmp_path / "x.npy"
    np.save(path, shown.astype(np.float32))
    prepared = prepare_xray(path, volume=vol, center_lps=c, init_params=np.zeros(6), size=(64, 64))
    assert prepared.image.shape != (96, 96)  # the optimiser's image is the crop
    field = _Oracle(None, "field")
    assert network_view(field, prepared) is None
    view = network_view(_Oracle(None, "detector"), prepared)
    assert view.image.shape == view.mask.shape == (32, 32)
    assert view.geometry.height == 32 and abs(view.geometry.pixel_spacing_mm - 3 * r.geometry.pixel_spacing_mm) < 1e-9
    # the field's place on the detector is kept: its centroid about 0.45 of the width, 0.5 of the height
    rows, cols = np.nonzero(view.mask)
    assert abs(cols.mean() / 32 - 0.45) < 0.04 and abs(rows.mean() / 32 - 0.5) < 0.04
    assert 0.15 < view.mask.mean() < 0.4  # pi 0.3^2 = 0.28 of the detector
