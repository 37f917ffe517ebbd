"""What the network is shown: a field-framed network the optimiser's crop masked by the field with its
clipped plateaus kept (only drawn overlays removed); a network framed by the detector
(train.framing = "detector") the X-ray's whole detector at its own size, the field masked, and DRRs
rendered for that detector, while CMA-ES keeps the crop."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import ndimage

from register.engines.contextual import ContextualRegistration, ContextualSettings
from register.xray.network_view import NetworkView, network_view


@pytest.fixture(scope="module")
def phantom():
    from sim.ct.anatomy import anatomy_center
    from sim.ct.phantom import make_pelvis_phantom

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
    from sim.projection.geometry import pose_from_params
    from sim.projection.scene import load_scene
    from sim.projection.se3 import rotation_error_deg

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
    from sim.projection.geometry import pose_from_params
    from sim.physics.display import Collimator
    from sim.projection.drr import DRRRenderer, RenderSettings

    vol, c = phantom
    r = DRRRenderer(vol, RenderSettings(size=(96, 96)), center_lps=c)
    img = r.render(pose_from_params(np.zeros((1, 6)), r.geometry.sod_mm))[0]
    col = Collimator(shape="circle", radius=0.3, center=(0.45, 0.5))
    shown = np.where(col.mask(96, 96), img, 0.0)
    path = tmp_path / "x.npy"
    np.save(path, shown.astype(np.float32))
    prepared = prepare_xray(path, volume=vol, center_lps=c, init_params=np.zeros(6), size=(64, 64))
    assert prepared.image.shape != (96, 96)  # the optimiser's image is the crop
    field = network_view(_Oracle(None, "field"), prepared)
    assert field.geometry == prepared.geometry and field.mask.shape == prepared.image.shape
    view = network_view(_Oracle(None, "detector"), prepared)
    assert view.image.shape == view.mask.shape == (32, 32)
    assert view.geometry.height == 32 and abs(view.geometry.pixel_spacing_mm - 3 * r.geometry.pixel_spacing_mm) < 1e-9
    # the field's place on the detector is kept: its centroid about 0.45 of the width, 0.5 of the height
    rows, cols = np.nonzero(view.mask)
    assert abs(cols.mean() / 32 - 0.45) < 0.04 and abs(rows.mean() / 32 - 0.5) < 0.04
    assert 0.15 < view.mask.mean() < 0.4  # pi 0.3^2 = 0.28 of the detector


def test_a_field_framed_network_sees_the_clipped_plateaus_but_not_the_text(phantom, tmp_path):
    """Registration's valid pixels drop saturated plateaus and overlays (intensity similarities cannot
    use them); the network's training targets keep their clipped pixels, so the network is shown the
    field with its plateaus, only the drawn text removed, at the same crop, size and geometry, and
    the contextual iteration renders one DRR per step for both."""
    from PIL import Image, ImageDraw

    from register.xray.prepare import prepare_xray
    from sim.projection.drr import DRRRenderer, RenderSettings
    from sim.projection.geometry import pose_from_params
    from sim.physics.display import Collimator

    vol, c = phantom
    r = DRRRenderer(vol, RenderSettings(size=(128, 128)), center_lps=c)
    img = r.render(pose_from_params(np.zeros((1, 6)), r.geometry.sod_mm))[0]
    field = Collimator(shape="circle", radius=0.42, center=(0.5, 0.5)).mask(128, 128)
    top = np.percentile(img[field], 80)  # the brightest fifth of the field clipped: a saturated plateau
    shown = np.where(field, np.minimum(img, top) / top * 4095.0 + 200.0, 0.0)
    canvas = Image.new("L", (128, 128), 0)
    ImageDraw.Draw(canvas).text((30, 90), "AP 1234", fill=255)
    text = np.asarray(canvas) > 0
    shown[text & field] = 0.0  # burned-in black text over the anatomy
    plateau = field & (img >= top) & ~text
    path = tmp_path / "x.npy"
    np.save(path, shown.astype(np.float32))
    prepared = prepare_xray(path, volume=vol, center_lps=c, init_params=np.zeros(6), size=(128, 128))
    assert prepared.image.shape == prepared.network_image.shape == prepared.network_mask.shape
    # the truth at the optimiser's pixel centres (fit_to_size's sampling of the crop)
    r0, r1, c0, c1 = next(e["measured"]["crop_box"] for e in prepared.record if e["step"] == "crop")
    h, w = prepared.image.shape
    f = min((r1 - r0) / h, (c1 - c0) / w)
    rows = np.round(r0 + ((r1 - r0) - h * f) / 2 + (np.arange(h) + 0.5) * f - 0.5).astype(int)
    cols = np.round(c0 + ((c1 - c0) - w * f) / 2 + (np.arange(w) + 0.5) * f - 0.5).astype(int)
    on = lambda m: m[np.ix_(rows, cols)]
    inner = on(ndimage.binary_erosion(plateau, iterations=3))
    near_text = on(ndimage.binary_dilation(text, iterations=2) & field)
    assert inner.sum() > 100 and near_text.sum() > 50
    assert not prepared.mask[inner].any(), "the valid pixels drop the plateau"
    # the plateau's thin parts count as overlays (module doc of register.xray.field): most of it is shown
    assert prepared.network_mask[inner].mean() > 0.7, "the network sees the plateau"
    assert not prepared.network_mask[near_text].any() and not prepared.mask[near_text].any(), "nor the text"
    assert (prepared.network_mask | ~prepared.mask).all()  # the network's pixels include the valid ones
    shown_plateau = inner & prepared.network_mask
    assert prepared.network_image[shown_plateau].min() > 0.99  # the clipped level, normalised to 1

    truth = np.array([10.0, -5.0, 3.0, 10.0, -10.0, 15.0])
    oracle = _Oracle(pose_from_params(truth, r.geometry.sod_mm), "field")
    reg = ContextualRegistration(vol, oracle, ContextualSettings(max_iterations=5), size=prepared.image.shape,
                                 geometry=prepared.geometry, center_lps=c)
    oracle.watch(reg.renderer)
    view = network_view(oracle, prepared)
    np.testing.assert_array_equal(view.mask, prepared.network_mask)
    result = reg.register(prepared.image, np.zeros(6), mask=prepared.mask, network_view=view)
    assert not reg._view_renderers  # the view's detector is the registration's: no second renderer
    assert result.renders == len(oracle.shapes) + 1
