"""Collimator masks and the display chain against truth: analytic areas (circle, clipped circle,
rotated rectangle, shoelace polygon), exact pixel-centre masks on tiny images, the blade
transmission, and the display mapping of a synthetic raw signal ``I0 exp(-L)`` with an analytic
``L`` (Gaussian blobs): affine window, polarity, gamma, quantisation, shutter, unsharp masking."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from sim.physics import PhysicsError
from sim.physics.display import Collimator, DisplayChain

I0 = 5.0e4  # flat-field signal (keV per pixel)


def blobs(h: int = 256, w: int = 320) -> np.ndarray:
    """Analytic line integral L: a sum of Gaussian blobs over a constant (smooth, no ties)."""
    y, x = np.mgrid[0:h, 0:w] + 0.5
    L = 0.3 + 0.05 * x / w
    for cx, cy, s, a in ((0.5, 0.5, 0.15, 2.0), (0.3, 0.35, 0.06, 1.2), (0.7, 0.6, 0.08, 0.8)):
        L = L + a * np.exp(-((x - cx * w) ** 2 + (y - cy * h) ** 2) / (2 * (s * min(h, w)) ** 2))
    return L


def window_truth(L: np.ndarray, field: np.ndarray, window=(1.0, 99.0)) -> np.ndarray:
    """The windowed [0, 1] value of L (bone-bright orientation), percentiles over the field."""
    lo, hi = np.percentile(L[field], window)
    return np.clip((L - lo) / (hi - lo), 0.0, 1.0)


# --------------------------------------------------------------------------------------------
# collimator masks
# --------------------------------------------------------------------------------------------


def test_circle_area_is_pi_r_squared():
    h, w = 400, 600
    m = Collimator("circle", center=(0.5, 0.5), radius=0.45).mask(h, w)
    r = 0.45 * min(h, w)
    assert m.shape == (h, w) and m.dtype == bool
    assert m.sum() == pytest.approx(math.pi * r * r, rel=0.01)


def test_off_centre_circle_is_clipped_by_the_image():
    """A circle centred at x = 0.9 W with radius 0.3 H (H < W) crosses the right edge: the mask
    area is pi r^2 minus the analytic circular segment beyond the edge."""
    h, w = 400, 600
    col = Collimator("circle", center=(0.9, 0.5), radius=0.3)
    m = col.mask(h, w)
    r, d = 0.3 * h, w - 0.9 * w  # distance from the centre to the right edge
    segment = r * r * math.acos(d / r) - d * math.sqrt(r * r - d * d)
    truth = math.pi * r * r - segment
    assert m.sum() == pytest.approx(truth, rel=0.01)
    assert m.sum() < 0.9 * math.pi * r * r  # really clipped
    assert m[:, -1].any() and not m[:, 0].any()  # x is the column: the field touches the right edge


def test_rectangle_and_rotated_rectangle_areas_and_sense_of_rotation():
    h, w = 400, 600
    m = Collimator("rectangle", center=(0.5, 0.5), half_size=(0.3, 0.2)).mask(h, w)
    a, b = 0.3 * w, 0.2 * h
    assert m.sum() == pytest.approx(4 * a * b, rel=0.01)
    assert m[:, int(0.5 * w - a) + 2].any() and not m[:, int(0.5 * w - a) - 2].any()  # half width on columns
    # rotated 30 deg, inside a square image: the area is kept
    n = 512
    rot = Collimator("rectangle", half_size=(0.25, 0.15), rotation_deg=30.0)
    mr = rot.mask(n, n)
    assert mr.sum() == pytest.approx(4 * 0.25 * n * 0.15 * n, rel=0.01)
    # counter-clockwise as displayed (rows go down): the long axis points up-right
    c = n / 2
    up_right = (int(c - 120 * math.sin(math.radians(30))), int(c + 120 * math.cos(math.radians(30))))
    down_right = (int(c + 120 * math.sin(math.radians(30))), int(c + 120 * math.cos(math.radians(30))))
    assert mr[up_right] and not mr[down_right]
    # 90 deg swaps the half sizes on a square image
    m90 = Collimator("rectangle", half_size=(0.25, 0.15), rotation_deg=90.0).mask(n, n)
    assert np.array_equal(m90, Collimator("rectangle", half_size=(0.15, 0.25)).mask(n, n))


def test_iris_with_blades_area_is_the_circle_less_two_segments():
    """An iris of radius r cut by two parallel blades at distance d from its centre (rotated 25 deg)
    keeps pi r^2 minus two circular segments, each r^2 acos(d / r) - d sqrt(r^2 - d^2) (closed
    form; 1 % covers the pixel staircase at r = 200 px); every pixel is inside both the circle
    and the blades' rectangle."""
    n = 512
    r_frac, d_frac = 0.4, 0.25  # radius: of the shorter side; blade distance: half height, of the height
    col = Collimator("iris-blades", center=(0.5, 0.5), radius=r_frac, half_size=(2.0, d_frac), rotation_deg=25.0)
    m = col.mask(n, n)
    r, d = r_frac * n, d_frac * n
    segment = r * r * math.acos(d / r) - d * math.sqrt(r * r - d * d)
    assert m.sum() == pytest.approx(math.pi * r * r - 2 * segment, rel=0.01)
    circle = Collimator("circle", center=(0.5, 0.5), radius=r_frac).mask(n, n)
    blades = Collimator("rectangle", center=(0.5, 0.5), half_size=(2.0, d_frac), rotation_deg=25.0).mask(n, n)
    assert np.array_equal(m, circle & blades)
    # blades wider than the circle leave the circle
    assert np.array_equal(Collimator("iris-blades", radius=0.3, half_size=(0.5, 0.5)).mask(64, 64),
                          Collimator("circle", radius=0.3).mask(64, 64))


def test_polygon_area_is_the_shoelace_area():
    h, w = 300, 500
    verts = ((0.2, 0.1), (0.7, 0.15), (0.9, 0.5), (0.75, 0.9), (0.3, 0.85), (0.1, 0.45))
    p = np.asarray(verts) * [w, h]
    shoelace = 0.5 * abs(np.sum(p[:, 0] * np.roll(p[:, 1], -1) - np.roll(p[:, 0], -1) * p[:, 1]))
    for order in (verts, verts[::-1]):  # either orientation
        m = Collimator("polygon", vertices=order).mask(h, w)
        assert m.sum() == pytest.approx(shoelace, rel=0.01)


def test_pixel_centre_convention_on_tiny_images():
    # circle of radius 1.2 px at the centre of 5 x 5: the centre pixel and its 4 neighbours
    m = Collimator("circle", radius=0.24).mask(5, 5)
    truth = np.zeros((5, 5), bool)
    truth[2, 1:4] = truth[1:4, 2] = True
    assert np.array_equal(m, truth)
    # circle of radius 2 px centred on the top-left corner of 4 x 6: centres (0.5, 0.5) at
    # 0.71 px, (1.5, 0.5) and (0.5, 1.5) at 1.58 px are inside, (1.5, 1.5) at 2.12 px is not
    m = Collimator("circle", center=(0.0, 0.0), radius=0.5).mask(4, 6)
    truth = np.zeros((4, 6), bool)
    truth[0, :2] = truth[1, 0] = True
    assert np.array_equal(m, truth)
    # rectangle on 2 x 4: centre (1, 1) px, half sizes 1 px: columns 0 and 1 (x is the column)
    m = Collimator("rectangle", center=(0.25, 0.5), half_size=(0.25, 0.5)).mask(2, 4)
    assert np.array_equal(m, np.array([[1, 1, 0, 0], [1, 1, 0, 0]], bool))
    # triangle (0,0), (1,0), (0,1) of a 4 x 4 image: pixel centres with x + y <= 4
    m = Collimator("polygon", vertices=((0, 0), (1, 0), (0, 1))).mask(4, 4)
    r, c = np.mgrid[0:4, 0:4]
    assert np.array_equal(m, (c + 0.5) + (r + 0.5) <= 4)
    assert Collimator("none").mask(3, 7).all()


def test_collimator_apply_scales_only_the_outside():
    rng = np.random.default_rng(0)
    raw = (I0 * np.exp(-blobs(64, 80)) * rng.uniform(0.9, 1.1, (64, 80))).astype(np.float32)
    col = Collimator("circle", radius=0.4, transmission=0.03)
    m = col.mask(64, 80)
    out = col.apply(raw)
    assert out.shape == raw.shape and out.dtype == np.float32
    assert np.array_equal(out[m], raw[m])
    np.testing.assert_array_equal(out[~m], raw[~m] * np.float32(0.03))
    batch = np.stack([raw, 2 * raw])
    ob = col.apply(batch)
    assert ob.shape == (2, 64, 80)
    assert np.array_equal(ob[1][m], 2 * raw[m]) and np.allclose(ob[1][~m], 2 * raw[~m] * 0.03, rtol=1e-6)
    assert np.array_equal(Collimator("none").apply(raw), raw)


# --------------------------------------------------------------------------------------------
# display chain
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def scene():
    """Raw signal of the blobs through a circular collimator, with the field and L."""
    L = blobs()
    col = Collimator("circle", radius=0.42, transmission=0.02)
    raw = col.apply(I0 * np.exp(-L))
    return L, raw, col.mask(*L.shape)


def test_log_bone_bright_is_affine_in_L_over_the_field_window(scene):
    L, raw, field = scene
    chain = DisplayChain(log=True, polarity="bone-bright", gamma=1.0, bits=16, shutter="none")
    out = chain.apply(raw, I0, field)
    assert out.dtype == np.uint16 and out.shape == L.shape
    M = 2**16 - 1
    # percentiles of the field only: outside, the shadow's L - log(0.02) would move hi
    t = window_truth(L - np.log(np.where(field, 1.0, 0.02)), field)
    # exact: round(t M), up to the rounding of -log(raw / I0) vs L (1 level at an exact tie)
    assert np.abs(out.astype(np.int64) - np.rint(t * M)).max() <= 1
    assert np.all(out[~field] == M)  # the shadow is above the window: bright in bone-bright
    unclipped = field & (t > 0) & (t < 1)
    assert unclipped.sum() > 0.9 * field.sum()
    assert np.corrcoef(out[unclipped].astype(np.float64), L[unclipped])[0, 1] > 0.9999
    # 1 % of the field pixels at each end of the window is clipped
    assert (out[field] == 0).mean() == pytest.approx(0.01, abs=0.002)
    assert (out[field] == M).mean() == pytest.approx(0.01, abs=0.002)


def test_bone_dark_is_the_reverse_of_bone_bright(scene):
    L, raw, field = scene
    for bits in (16, 12, 8):
        bright = DisplayChain(polarity="bone-bright", bits=bits, shutter="none").apply(raw, I0, field)
        dark = DisplayChain(polarity="bone-dark", bits=bits, shutter="none").apply(raw, I0, field)
        assert np.all(bright.astype(np.int64) + dark == 2**bits - 1)
    # bone-dark: the densest blob centre is darker than the background
    assert dark[128, 160] < dark[field].mean()


def test_gamma_maps_the_window_midpoint_to_sqrt_half():
    """An L ramp with an odd number of values: window (0, 100) puts min, max and the exact
    midpoint in the image; gamma 0.5 maps the midpoint to round(sqrt(0.5) M) and every pixel
    to round(t^0.5 M)."""
    L = np.linspace(0.5, 2.5, 101)[None, :].repeat(3, axis=0)
    raw = I0 * np.exp(-L)
    M = 2**16 - 1
    out = DisplayChain(polarity="bone-bright", window=(0.0, 100.0), gamma=0.5, bits=16).apply(raw, I0, None)
    assert out[1, 50] == round(math.sqrt(0.5) * M)
    t = (L - 0.5) / 2.0
    assert np.abs(out.astype(np.int64) - np.rint(np.sqrt(t) * M)).max() <= 1
    assert out[0, 0] == 0 and out[0, -1] == M
    dark = DisplayChain(polarity="bone-dark", window=(0.0, 100.0), gamma=0.5, bits=16).apply(raw, I0, None)
    assert dark[1, 50] == round(math.sqrt(0.5) * M)  # gamma acts on the displayed brightness
    assert dark[0, 0] == M and dark[0, -1] == 0


def test_quantisation(scene):
    L, raw, field = scene
    for bits in (8, 10):
        out = DisplayChain(bits=bits, shutter="none").apply(raw, I0, field)
        assert out.dtype == np.uint16
        assert len(np.unique(out)) <= 2**bits
        assert out.max() == 2**bits - 1 and out.min() == 0
    out8 = DisplayChain(bits=8, polarity="bone-bright").apply(raw, I0, field)
    t = window_truth(L, field)
    assert np.abs(out8[field].astype(np.int64) - np.rint(t[field] * 255)).max() <= 1
    assert len(np.unique(out8[field])) > 200  # the window fills the range


def test_shutter_outside_values(scene):
    L, raw, field = scene
    black = DisplayChain(shutter="black", bits=12).apply(raw, I0, field)
    white = DisplayChain(shutter="white", bits=12).apply(raw, I0, field)
    none = DisplayChain(shutter="none", bits=12).apply(raw, I0, field)
    assert np.all(black[~field] == 0) and np.all(white[~field] == 4095)
    assert np.array_equal(black[field], none[field]) and np.array_equal(white[field], none[field])
    # none: the collimator shadow as the physics gives it, windowed like the field; in the
    # bone-dark log image, the shadow (L - log 0.02 above the window) is clipped to black
    t = window_truth(L - np.log(np.where(field, 1.0, 0.02)), field)
    assert np.abs(none.astype(np.int64) - np.rint((1 - t) * 4095)).max() <= 1
    assert np.all(none[~field] == 0)
    # with a transparent collimator the outside is the plain image: not clipped
    raw1 = Collimator("circle", radius=0.42, transmission=1.0).apply(I0 * np.exp(-L))
    none1 = DisplayChain(shutter="none", bits=12).apply(raw1, I0, field)
    t1 = window_truth(L, field)
    assert np.abs(none1[~field].astype(np.int64) - np.rint((1 - t1[~field]) * 4095)).max() <= 1
    assert len(np.unique(none1[~field])) > 50


def test_unsharp_masking_overshoots_at_an_edge_and_keeps_flat_regions():
    """A step L = 1 | 2 with L = 0 and 3 strips (so that the step lies inside the window): the
    unsharp mask makes the dark side darker and the bright side brighter next to the edge,
    and leaves pixels far from any edge (> 5 sigma) as they were."""
    h, w = 64, 200
    L = np.ones((h, w))
    L[:, 100:] = 2.0
    L[:, :10] = 0.0
    L[:, 190:] = 3.0
    raw = I0 * np.exp(-L)
    plain = DisplayChain(polarity="bone-bright", bits=16).apply(raw, I0, None).astype(np.int64)
    sharp = DisplayChain(polarity="bone-bright", bits=16, unsharp_sigma_px=3.0,
                         unsharp_amount=1.0).apply(raw, I0, None).astype(np.int64)
    M = 2**16 - 1
    assert plain[0, 50] == round(M / 3) and plain[0, 150] == round(2 * M / 3)
    # overshoot on both sides of the edge between columns 99 and 100
    assert sharp[32, 99] < plain[32, 99] - 0.05 * M
    assert sharp[32, 100] > plain[32, 100] + 0.05 * M
    contrast_plain = plain[32, 100] - plain[32, 99]
    assert sharp[32, 100] - sharp[32, 99] > 1.2 * contrast_plain
    # flat regions unchanged (within a rounding level)
    flat = np.zeros(w, bool)
    flat[[*range(26, 84), *range(116, 174)]] = True
    assert np.abs(sharp[:, flat] - plain[:, flat]).max() <= 1


def test_unsharp_ignores_the_collimator_edge():
    """With a field, the blur is a normalised convolution inside it: a flat object behind a
    collimator keeps its value up to the field edge (no halo from the shadow). Two single
    pixels set the window (0, 100) to L in [0.5, 2], so the object's 1 | 1.5 sits mid-range and
    a halo would not be clipped away."""
    L = np.full((128, 128), 1.0)
    L[:, 64:] = 1.5
    L[64, 30], L[64, 100] = 0.5, 2.0
    col = Collimator("circle", radius=0.45, transmission=0.02)
    raw = col.apply(I0 * np.exp(-L))
    field = col.mask(128, 128)
    M = 2**16 - 1
    kw = dict(polarity="bone-bright", bits=16, shutter="none", window=(0.0, 100.0))
    plain = DisplayChain(**kw).apply(raw, I0, field).astype(np.int64)
    sharp = DisplayChain(**kw, unsharp_sigma_px=2.0, unsharp_amount=1.0).apply(raw, I0, field).astype(np.int64)
    assert plain[64, 40] == round(M / 3) and plain[64, 80] == round(2 * M / 3)
    far = field.copy()
    far[:, 52:76] = False  # away from the object's step and from the two window pixels
    far[54:75, 20:41] = far[54:75, 90:111] = False
    assert np.abs(sharp[far] - plain[far]).max() <= 1
    assert (far & ~np.roll(field, 3, axis=1)).any()  # far includes pixels next to the field edge


def test_linear_output_is_monotone_in_intensity():
    I = np.linspace(0.05, 1.0, 400) * I0
    raw = np.tile(I, (4, 1))[:, np.random.default_rng(1).permutation(400)]
    order = np.argsort(raw[0])
    dark = DisplayChain(log=False, polarity="bone-dark", bits=16).apply(raw, I0, None)[0][order]
    bright = DisplayChain(log=False, polarity="bone-bright", bits=16).apply(raw, I0, None)[0][order]
    assert np.all(np.diff(dark.astype(np.int64)) >= 0) and dark[-1] > dark[0]  # bright where I is high
    assert np.all(np.diff(bright.astype(np.int64)) <= 0) and bright[-1] < bright[0]
    # linear: affine in I inside the window
    inside = (dark > 0) & (dark < 2**16 - 1)
    assert np.corrcoef(dark[inside].astype(np.float64), raw[0][order][inside])[0, 1] > 0.9999


def test_batch_frames_are_windowed_each_on_its_own(scene):
    L, raw, field = scene
    chain = DisplayChain(bits=12)
    out = chain.apply(np.stack([raw, 0.5 * raw]), I0, field)
    assert out.shape == (2, *L.shape)
    # halving the signal shifts L by log 2: the per-frame window makes the images equal
    assert np.abs(out[0].astype(np.int64) - out[1]).max() <= 1
    assert np.array_equal(out[0], chain.apply(raw, I0, field))


# --------------------------------------------------------------------------------------------
# settings: validation and JSON round trip
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kwargs, name", [
    (dict(gamma=0.0), "gamma"), (dict(gamma=-1.0), "gamma"), (dict(gamma=float("nan")), "gamma"),
    (dict(bits=20), "bits"), (dict(bits=7), "bits"), (dict(bits=12.0), "bits"), (dict(bits=True), "bits"),
    (dict(polarity="bone-grey"), "polarity"), (dict(shutter="grey"), "shutter"),
    (dict(window=(99.0, 1.0)), "window"), (dict(window=(-1.0, 99.0)), "window"),
    (dict(window=(1.0, float("nan"))), "window"), (dict(window=(1.0,)), "window"),
    (dict(unsharp_amount=1.0), "unsharp_sigma_px"), (dict(unsharp_amount=-0.5, unsharp_sigma_px=1.0), "unsharp_amount"),
    (dict(unsharp_sigma_px=float("inf")), "unsharp_sigma_px"), (dict(log="yes"), "log"),
])
def test_bad_display_settings_raise_naming_the_setting(kwargs, name):
    with pytest.raises(PhysicsError, match=name):
        DisplayChain(**kwargs)


@pytest.mark.parametrize("kwargs, name", [
    (dict(radius=0.0), "radius"), (dict(radius=-0.1), "radius"), (dict(radius=float("nan")), "radius"),
    (dict(shape="ellipse"), "shape"), (dict(center=(0.5, float("nan"))), "center"),
    (dict(center=(1.5, 0.5)), "center"), (dict(half_size=(0.0, 0.3)), "half_size"),
    (dict(transmission=1.5), "transmission"), (dict(transmission=float("nan")), "transmission"),
    (dict(rotation_deg=float("inf")), "rotation_deg"),
    (dict(shape="polygon", vertices=((0.1, 0.1), (0.9, 0.1))), "vertices"),
    (dict(shape="polygon"), "vertices"),
    (dict(shape="polygon", vertices=((0.1, 0.1), (0.9, 0.1), (0.5, 0.4), (0.5, 0.9))), "convex"),
    (dict(shape="polygon", vertices=((0.5, 0.0), (0.6, 0.9), (0.0, 0.3), (1.0, 0.3), (0.4, 0.9))), "convex"),
    (dict(shape="polygon", vertices=((0.1, 0.1), (0.5, 0.5), (0.9, 0.9))), "vertices"),
    (dict(shape="polygon", vertices=((0.1, 0.1), (0.9, float("nan")), (0.5, 0.9))), "vertices"),
])
def test_bad_collimator_settings_raise_naming_the_setting(kwargs, name):
    with pytest.raises(PhysicsError, match=name):
        Collimator(**kwargs)


def test_bad_inputs_raise():
    chain = DisplayChain()
    img = np.ones((8, 8))
    with pytest.raises(PhysicsError, match="i0"):
        chain.apply(img, 0.0, None)
    with pytest.raises(PhysicsError, match="field"):
        chain.apply(img, 1.0, np.ones((8, 9), bool))
    with pytest.raises(PhysicsError, match="field"):
        chain.apply(img, 1.0, np.zeros((8, 8), bool))
    with pytest.raises(PhysicsError, match="finite"):
        chain.apply(np.full((8, 8), np.nan), 1.0, None)
    with pytest.raises(PhysicsError, match="height"):
        Collimator().mask(0, 8)


def test_json_round_trip():
    cols = [Collimator(), Collimator("rectangle", center=(0.4, 0.6), half_size=(0.3, 0.2), rotation_deg=15.0),
            Collimator("polygon", vertices=((0.2, 0.1), (0.8, 0.2), (0.5, 0.9)), transmission=0.0),
            Collimator("none")]
    for c in cols:
        d = json.loads(json.dumps(c.to_dict()))
        assert Collimator.from_dict(d) == c
    chains = [DisplayChain(), DisplayChain(log=False, polarity="bone-bright", window=(2.0, 98.0), gamma=0.7,
                                           unsharp_sigma_px=2.5, unsharp_amount=0.8, bits=16, shutter="none")]
    for ch in chains:
        d = json.loads(json.dumps(ch.to_dict()))
        assert DisplayChain.from_dict(d) == ch
    assert Collimator.from_dict({"shape": "circle", "radius": 0.3}) == Collimator(radius=0.3)
    with pytest.raises(PhysicsError, match="radiuss"):
        Collimator.from_dict({"radiuss": 0.3})
    with pytest.raises(PhysicsError, match="gamma"):
        DisplayChain.from_dict({"gamma": 0})
