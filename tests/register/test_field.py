"""register.xray.field: collimated field detection and the valid-pixel mask, checked against truth.

Synthetic anatomy-like images (smooth random texture, blobs, noise) inside a known field (circle,
rectangle, polygon; clipped by the image edges or not), with the outside painted black or white
or a noisy raw shadow, in 8-bit, 12-bit and float. Truth distances are measured on a padded grid
so that a field boundary just beyond the image edge counts as a boundary.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from PIL import Image, ImageDraw, ImageFont
from scipy import ndimage

from register.xray.field import Field, FieldError, FieldSettings, detect_field, log_view
from register.xray.io import XRayInputError

PAD = 12


# ------------------------------------------------------------------------------------------
# synthetic images


def _anatomy(shape, seed, lo=0.25, hi=0.85, noise=0.01):
    """Anatomy-like texture in [lo, hi]: smooth random field + Gaussian blobs + pixel noise."""
    rng = np.random.default_rng(seed)
    H, W = shape
    t = ndimage.gaussian_filter(rng.normal(size=shape), 10)
    yy, xx = np.mgrid[:H, :W]
    t = (t - t.min()) / (t.max() - t.min())
    for _ in range(6):
        cy, cx = rng.uniform(0, H), rng.uniform(0, W)
        sy, sx = rng.uniform(5, 25, 2)
        t = t + rng.uniform(-0.4, 0.6) * np.exp(-(((yy - cy) / sy) ** 2 + ((xx - cx) / sx) ** 2))
    t = ndimage.gaussian_filter(t, 1.0)
    t = (t - t.min()) / (t.max() - t.min())
    span = hi - lo
    a = lo + 0.05 * span + 0.9 * span * t + rng.normal(0.0, noise, shape)
    return np.clip(a, lo, hi)


def _circle(cx, cy, r):
    def truth(shape, pad=0):
        yy, xx = np.mgrid[: shape[0], : shape[1]]
        return (xx - pad - cx) ** 2 + (yy - pad - cy) ** 2 <= r * r
    truth.circle = (cx, cy, r)
    return truth


def _rect(r0, r1, c0, c1):
    def truth(shape, pad=0):
        yy, xx = np.mgrid[: shape[0], : shape[1]]
        rr, cc = yy - pad, xx - pad
        # an edge on the image border continues beyond it
        r0e, r1e = (-10**6 if r0 == 0 else r0), (10**6 if r1 == shape[0] - 2 * pad else r1)
        c0e, c1e = (-10**6 if c0 == 0 else c0), (10**6 if c1 == shape[1] - 2 * pad else c1)
        return (rr >= r0e) & (rr < r1e) & (cc >= c0e) & (cc < c1e)
    return truth


def _regular_polygon(cx, cy, radius, n, rot):
    ang = rot + 2 * np.pi * np.arange(n) / n
    verts = np.column_stack([cx + radius * np.cos(ang), cy + radius * np.sin(ang)])  # (x, y)

    def truth(shape, pad=0):
        yy, xx = np.mgrid[: shape[0], : shape[1]]
        x, y = xx - pad, yy - pad
        inside = np.ones(shape, dtype=bool)
        for (x0, y0), (x1, y1) in zip(verts, np.roll(verts, -1, axis=0)):
            inside &= (x1 - x0) * (y - y0) - (y1 - y0) * (x - x0) >= 0
        return inside
    truth.vertices = verts
    return truth


def _compose(truth, anat, outside=0.0, blur=0.0, out_noise=0.0, seed=0):
    w = truth.astype(np.float64)
    if blur > 0:
        w = ndimage.gaussian_filter(w, blur)
    img = w * anat + (1.0 - w) * outside
    if out_noise > 0:
        img = img + (1.0 - w) * np.random.default_rng(seed + 99).normal(0.0, out_noise, truth.shape)
    return img


def _as(img, dtype):
    if dtype == "u8":
        return np.round(np.clip(img, 0, 1) * 255).astype(np.uint8)
    if dtype == "u12":
        return np.round(np.clip(img, 0, 1) * 4095).astype(np.uint16)
    return img.astype(np.float32)


def _boundary_distance(truth_fn, shape):
    """Distance (px) of every pixel to the truth boundary, the truth rendered with a margin."""
    big = truth_fn((shape[0] + 2 * PAD, shape[1] + 2 * PAD), PAD)
    d = np.where(big, ndimage.distance_transform_edt(big), ndimage.distance_transform_edt(~big))
    return d[PAD:-PAD, PAD:-PAD]


def _glyphs(shape, items):
    """Binary (aliased, as burned in by vendors) text / lines drawn with Pillow: (H, W) bool."""
    im = Image.new("L", (shape[1], shape[0]), 0)
    draw = ImageDraw.Draw(im)
    draw.fontmode = "1"
    for item in items:
        if item[0] == "text":
            draw.text(item[1], item[2], fill=255, font=item[3] if len(item) > 3 else None)
        else:
            draw.line(item[1], fill=255, width=item[2])
    return np.array(im) > 0


def _ruler(x0, x1, y):
    return [("line", [(x0, y), (x1, y)], 1)] + [
        ("line", [(x, y), (x, y - (8 if (x - x0) % 50 == 0 else 4))], 1) for x in range(x0, x1 + 1, 10)]


def _assert_matches_truth(f: Field, truth, dist, tol=3.0):
    wrong = (f.mask != truth) & (dist > tol)
    assert wrong.sum() == 0, f"{int(wrong.sum())} pixels farther than {tol} px from the truth boundary are wrong"


# ------------------------------------------------------------------------------------------
# fields of every kind

S = (256, 256)
S2 = (200, 300)

FIELD_CASES = {
    # name: (shape, truth, outside value, dtype, kind, outside colour, extra)
    "centred circle, black, float": (S, _circle(127.5, 127.5, 110), 0.0, "f", "circle", "black", {}),
    "circle clipped by top and right edges, 8-bit": (S, _circle(185, 75, 120), 0.0, "u8", "circle", "black", {}),
    "circle, white outside, 12-bit": (S, _circle(120, 133, 105), 1.0, "u12", "circle", "white", {}),
    "circle clipped top/bottom, non-square, white, float": (S2, _circle(160, 95, 105), 1.0, "f", "circle", "white", {}),
    "rectangle, black, 12-bit": (S, _rect(30, 220, 40, 200), 0.0, "u12", "rectangle", "black", {}),
    "off-centre rectangle at top/right edges, white, 8-bit": (S, _rect(0, 180, 60, 256), 1.0, "u8", "rectangle", "white", {}),
    "rectangle, non-square, black, float": (S2, _rect(20, 170, 35, 260), 0.0, "f", "rectangle", "black", {}),
    "hexagon, black, 8-bit": (S, _regular_polygon(128, 128, 115, 6, 0.2), 0.0, "u8", "polygon", "black", {}),
    "octagon, tilted, white, 12-bit": (S, _regular_polygon(126, 131, 120, 8, 0.1), 1.0, "u12", "polygon", "white", {}),
    "octagon clipped by the edges, float": (S, _regular_polygon(128, 128, 150, 8, 0.3), 0.0, "f", "polygon", "black", {}),
    "raw noisy dark shadow, float": (S, _circle(127.5, 127.5, 110), 0.06, "f", "circle", "black", {"out_noise": 0.015}),
    "soft edge (blur 1.5 px), 8-bit": (S, _circle(130, 125, 108), 0.0, "u8", "circle", "black", {"blur": 1.5}),
    "soft edge + noisy shadow, 12-bit": (S, _rect(25, 230, 20, 236), 0.05, "u12", "rectangle", "black",
                                         {"blur": 1.5, "out_noise": 0.01}),
}


@pytest.mark.parametrize("name", list(FIELD_CASES))
def test_field_of_each_kind_matches_truth(name):
    shape, truth_fn, outside, dtype, kind, colour, extra = FIELD_CASES[name]
    seed = sum(map(ord, name)) % 1000
    truth = truth_fn(shape)
    img = _as(_compose(truth, _anatomy(shape, seed), outside=outside, seed=seed, **extra), dtype)
    f = detect_field(img)
    assert f.kind == kind, f.params
    assert f.outside == colour
    dist = _boundary_distance(truth_fn, shape)
    _assert_matches_truth(f, truth, dist)
    # the field itself (before exclusions) also; and no exclusions on a clean image
    assert ((f.field_mask != truth) & (dist > 3)).sum() == 0
    assert f.excluded == {"overlay": 0, "saturated": 0, "empty": 0}
    # the margin: every valid pixel lies inside the truth (soft edges: within 1 px of it)
    assert not (f.mask & ~truth & (dist > 1)).any()
    json.dumps(f.to_dict())


@pytest.mark.parametrize("name", [n for n, c in FIELD_CASES.items() if c[4] == "circle"])
def test_circle_centre_and_radius(name):
    shape, truth_fn, outside, dtype, _, _, extra = FIELD_CASES[name]
    seed = sum(map(ord, name)) % 1000
    img = _as(_compose(truth_fn(shape), _anatomy(shape, seed), outside=outside, seed=seed, **extra), dtype)
    p = detect_field(img).params
    cx, cy, r = truth_fn.circle
    assert abs(p["centre_x"] - cx) <= 1.5 and abs(p["centre_y"] - cy) <= 1.5
    assert abs(p["radius"] - r) <= 1.5


# ------------------------------------------------------------------------------------------
# an iris cut by shutter blades; anatomy at the outside's level notching the field's edge


def _iris_blades(cx, cy, r, half, rot_deg):
    """Circle (cx, cy, r) px cut by two parallel blades at +-``half`` px from its centre, their
    normal rotated ``rot_deg`` from the rows' direction."""
    t = np.deg2rad(rot_deg)
    n = np.array([np.sin(t), np.cos(t)])  # (x, y) unit normal of the blades

    def truth(shape, pad=0):
        yy, xx = np.mgrid[: shape[0], : shape[1]]
        x, y = xx - pad - cx, yy - pad - cy
        return (x * x + y * y <= r * r) & (np.abs(x * n[0] + y * n[1]) <= half)
    truth.circle = (cx, cy, r)
    truth.blades = [(cx + sgn * half * n[0], cy + sgn * half * n[1], n) for sgn in (-1, 1)]  # (x, y, normal)
    return truth


def _notched(anat, truth, outside, seed, count=6, radius=12):
    """``anat`` with ``count`` discs of anatomy at the outside's level (1 % of the range from it,
    not on it) centred on the field's edge: dense bone shown dark next to a black outside."""
    rng = np.random.default_rng(seed)
    inner = truth & ~ndimage.binary_erosion(truth, iterations=3)
    yy, xx = np.mgrid[: truth.shape[0], : truth.shape[1]]
    out = anat.copy()
    level = outside + (0.01 if outside == 0.0 else -0.01)
    for py, px in np.argwhere(inner)[rng.integers(0, inner.sum(), count)]:
        out[(yy - py) ** 2 + (xx - px) ** 2 < radius ** 2] = level
    return out


IRIS_CASES = {
    # name: (shape, truth, outside value, dtype)
    "iris + blades 15 deg, black, 12-bit": (S, _iris_blades(128, 126, 118, 80, 15), 0.0, "u12"),
    "iris + blades -35 deg, white, 8-bit": (S, _iris_blades(120, 130, 125, 95, -35), 1.0, "u8"),
    "iris + blades, non-square, black, float": (S2, _iris_blades(150, 100, 110, 70, 0), 0.0, "f"),
}


@pytest.mark.parametrize("name", list(IRIS_CASES))
def test_notched_iris_with_blades_matches_truth(name):
    """Anatomy at the outside's level notches the edge (no shape model fits the candidate within
    0.5 px any more): the iris-with-blades model still finds the circle (centre and radius within
    1.5 px), both blades (their fitted edges within 1.5 px of the true lines) and the field
    (within 3 px of the truth boundary)."""
    shape, truth_fn, outside, dtype = IRIS_CASES[name]
    seed = sum(map(ord, name)) % 1000
    truth = truth_fn(shape)
    img = _as(_compose(truth, _notched(_anatomy(shape, seed), truth, outside, seed), outside=outside), dtype)
    f = detect_field(img)
    assert f.kind == "iris-blades", f.params
    dist = _boundary_distance(truth_fn, shape)
    assert ((f.field_mask != truth) & (dist > 3)).sum() == 0
    cx, cy, r = truth_fn.circle
    p = f.params
    assert abs(p["centre_x"] - cx) <= 1.5 and abs(p["centre_y"] - cy) <= 1.5 and abs(p["radius"] - r) <= 1.5
    assert len(p["blades"]) == 2
    for bx, by, n in truth_fn.blades:  # some found blade lies on each true line (pixel edges: +-0.5 px)
        off = [max(abs((x - bx) * n[0] + (y - by) * n[1]) for x, y in blade) for blade in p["blades"]]
        assert min(off) <= 1.5, off
    json.dumps(f.to_dict())


def test_notched_circle_is_a_circle_without_blades():
    truth_fn = _circle(130, 124, 112)
    truth = truth_fn(S)
    f = detect_field(_as(_compose(truth, _notched(_anatomy(S, 21), truth, 0.0, 21, count=8)), "u12"))
    assert f.kind == "circle" and "blades" not in f.params
    assert abs(f.params["radius"] - 112) <= 1.5
    assert ((f.field_mask != truth) & (_boundary_distance(truth_fn, S) > 3)).sum() == 0


def test_a_blade_cuts_off_only_the_outside():
    """A candidate missing a circular segment behind a straight rim: a blade when the segment is
    the outside region (grown from the border over the flat outside level), not when it is
    anatomy the candidate lost (dark anatomy near the outside level, as on a dark cine display)."""
    from register.xray.field import _contour, _fit_iris_blades

    circle = _circle(128, 128, 115)(S)
    yy, xx = np.mgrid[:256, :256]
    segment = circle & (xx + 0.4 * yy < 80)
    cand = circle & ~segment
    pts = _contour(cand)
    shadow = ~cand  # the segment belongs to the outside: a blade's shadow
    fit = _fit_iris_blades(cand, pts, FieldSettings(), shadow)
    assert fit is not None and len(fit[1]["blades"]) == 1
    assert ((fit[0] != cand) & (_boundary_distance(lambda shape, pad=0: np.pad(cand, pad), S) > 2)).sum() == 0
    anatomy = ~circle  # the outside is only what lies beyond the circle: the segment is anatomy
    fit = _fit_iris_blades(cand, pts, FieldSettings(), anatomy)
    assert fit is None or "blades" not in fit[1]

def test_rectangle_and_polygon_params():
    truth_fn = _rect(30, 220, 40, 200)
    f = detect_field(_compose(truth_fn(S), _anatomy(S, 5)))
    assert f.params == {"row0": 30, "row1": 220, "col0": 40, "col1": 200}
    for n in (6, 8):
        poly = _regular_polygon(128, 128, 115, n, 0.2)
        f = detect_field(_compose(poly(S), _anatomy(S, n)))
        assert f.kind == "polygon"
        found = np.array(f.params["vertices"])
        assert found.shape == (n, 2)
        # every true vertex has a found vertex within 1.5 px
        d = np.hypot(*(found[None, :, :] - poly.vertices[:, None, :]).transpose(2, 0, 1))
        assert d.min(axis=1).max() <= 1.5


def test_margin_setting_erodes_from_the_model_boundary():
    truth_fn = _circle(127.5, 127.5, 110)
    img = _compose(truth_fn(S), _anatomy(S, 7))
    dist = _boundary_distance(truth_fn, S)
    f0 = detect_field(img, FieldSettings(margin_px=0))
    f6 = detect_field(img, FieldSettings(margin_px=6))
    assert ((f0.field_mask != truth_fn(S)) & (dist > 1)).sum() == 0
    assert f6.field_mask.any() and not (f6.field_mask & (dist < 5) & truth_fn(S)).any()
    assert (f6.field_mask & ~(dist > 4)).sum() == 0
    assert (truth_fn(S) & (dist > 7) & ~f6.field_mask).sum() == 0


@pytest.mark.parametrize("margin", [0.0, 2.0, 6.0])
def test_margin_is_exact_for_a_circle(margin):
    cx, cy, r = 127.5, 127.5, 110.0
    img = _compose(_circle(cx, cy, r)(S), _anatomy(S, 7))
    f = detect_field(img, FieldSettings(margin_px=margin))
    yy, xx = np.mgrid[:256, :256]
    depth = r - np.hypot(xx - cx, yy - cy)  # exact distance inside the true circle, px
    assert depth[f.field_mask].min() >= margin - 0.6
    assert f.field_mask[depth >= margin + 0.6].all()


def test_margin_does_not_erode_at_the_image_edges():
    truth_fn = _rect(0, 256, 40, 200)  # shutters left and right only
    f = detect_field(_compose(truth_fn(S), _anatomy(S, 8)))
    assert f.kind == "rectangle"
    assert f.field_mask[0, 60:180].all() and f.field_mask[-1, 60:180].all()


# ------------------------------------------------------------------------------------------
# burned-in text, rulers, markers


@pytest.mark.parametrize("outside,dtype", [(0.0, "u8"), (1.0, "u12")])
@pytest.mark.parametrize("shape_name", ["circle", "octagon"])
def test_text_ruler_and_marker_are_excluded(outside, dtype, shape_name):
    truth_fn = _circle(130, 126, 116) if shape_name == "circle" else _regular_polygon(128, 128, 124, 8, 0.3)
    truth = truth_fn(S)
    top = 255 if dtype == "u8" else 4095
    img = _as(_compose(truth, _anatomy(S, 11), outside=outside), dtype)
    big = ImageFont.load_default(28)
    white = _glyphs(S, [("text", (2, 2), "PATIENT^NAME 12345"),        # outside corner
                        ("text", (80, 110), "Lij 12.5 kV 3.2 mA"),     # over the anatomy
                        ("text", (190, 55), "L", big)]                 # side marker
                    + _ruler(60, 190, 200))
    black = _glyphs(S, [("text", (150, 242), "SIEMENS Cios"),         # outside corner
                        ("text", (60, 150), "AP 2024-01-01")])        # over the anatomy
    img[white] = top
    img[black] = 0
    f = detect_field(img)
    assert f.kind == ("circle" if shape_name == "circle" else "polygon")
    assert f.outside == ("black" if outside == 0.0 else "white")
    dist = _boundary_distance(truth_fn, S)
    assert ((f.field_mask != truth) & (dist > 3)).sum() == 0
    glyph = white | black
    assert (f.mask & glyph).sum() == 0, "glyph pixels inside the field must be excluded"
    far = truth & (dist > 3) & (ndimage.distance_transform_edt(~glyph) > 6)
    assert far.sum() > 0.6 * truth.sum()
    assert f.mask[far].all(), f"{int((~f.mask[far]).sum())} pixels far from glyphs were excluded"
    assert f.excluded["overlay"] > (glyph & f.field_mask).sum()
    assert f.excluded["saturated"] == 0 and f.excluded["empty"] == 0
    assert not (f.field_mask & ~f.overlay & glyph).any()  # the overlay mask holds the glyphs
    assert int(f.overlay.sum()) == f.excluded["overlay"]


def test_text_crossing_the_field_edge_does_not_bend_the_field():
    truth_fn = _rect(20, 236, 10, 240)
    truth = truth_fn(S)
    img = _as(_compose(truth, _anatomy(S, 12), outside=1.0), "u12")
    white = _glyphs(S, [("text", (195, 14), "EDGE TEXT"), ("text", (225, 120), "BORDER")])
    img[white] = 4095
    f = detect_field(img)
    assert f.kind == "rectangle" and f.params == {"row0": 20, "row1": 236, "col0": 10, "col1": 240}
    assert (f.mask & white).sum() == 0


def test_text_without_collimation():
    img = _as(_anatomy(S, 13), "u8")
    text = _glyphs(S, [("text", (3, 3), "R  ACC 0042"), ("text", (100, 120), "35 cm")])
    img[text] = 255
    f = detect_field(img)
    assert f.kind == "none" and f.outside is None
    assert (f.mask & text).sum() == 0
    assert f.valid_fraction > 0.95


# ------------------------------------------------------------------------------------------
# saturated and empty plateaus, raw noise


def test_saturated_plateau_is_excluded():
    truth_fn = _circle(127.5, 127.5, 112)
    truth = truth_fn(S)
    anat = _anatomy(S, 3)
    yy, xx = np.mgrid[:256, :256]
    anat = anat + 0.6 * np.exp(-(((xx - 150) / 24.0) ** 2 + ((yy - 100) / 16.0) ** 2))  # a bright implant
    img = _as(np.minimum(_compose(truth, anat), 0.95) / 0.95, "u8")  # clipped at the maximum
    plateau = (img == 255) & truth
    lab, n = ndimage.label(plateau, np.ones((3, 3)))
    sizes = np.bincount(lab.ravel())
    sizes[0] = 0
    big = np.isin(lab, np.nonzero(sizes >= 20)[0])
    assert big.sum() > 300
    f = detect_field(img)
    assert f.kind == "circle"
    assert not (f.mask & big).any()
    assert f.excluded["saturated"] >= big.sum() and f.excluded["overlay"] == 0
    assert not f.overlay.any()  # a plateau is no overlay: the network's mask keeps it
    dist = _boundary_distance(truth_fn, S)
    far = truth & (dist > 3) & (ndimage.distance_transform_edt(~plateau) > 5)
    assert f.mask[far].all()


def test_empty_plateau_is_excluded():
    truth_fn = _circle(127.5, 127.5, 112)
    truth = truth_fn(S)
    anat = _anatomy(S, 4)
    yy, xx = np.mgrid[:256, :256]
    hole = (xx - 100) ** 2 + (yy - 140) ** 2 < 20 ** 2
    anat[hole] = 0.0  # clipped to the minimum, as the black outside
    f = detect_field(_as(_compose(truth, anat), "u12"))
    assert f.kind == "circle" and f.outside == "black"
    assert not (f.mask & hole).any()
    assert f.excluded["empty"] >= hole.sum()
    dist = _boundary_distance(truth_fn, S)
    _assert_matches_truth(f, truth & ~ndimage.binary_dilation(hole, iterations=3), np.minimum(
        dist, ndimage.distance_transform_edt(~hole)))


@pytest.mark.parametrize("dtype", ["f", "u12", "u8"])
def test_raw_noisy_image_keeps_its_field(dtype):
    truth_fn = _circle(127.5, 127.5, 115)
    truth = truth_fn(S)
    anat = _anatomy(S, 21, lo=0.3, hi=0.95, noise=0.04)
    img = _as(_compose(truth, anat, outside=0.05, out_noise=0.02, seed=3), dtype)
    f = detect_field(img)
    assert f.kind == "circle" and f.outside == "black"
    assert (f.mask & truth).sum() > 0.95 * truth.sum()
    assert f.mask.sum() == f.field_mask.sum()  # no pixel of the noisy field excluded
    assert f.excluded == {"overlay": 0, "saturated": 0, "empty": 0}


# ------------------------------------------------------------------------------------------
# no collimation


@pytest.mark.parametrize("seed,shape,dtype", [(1, S, "f"), (5, S, "u8"), (6, S2, "u12"), (9, (300, 220), "f")])
def test_no_collimator(seed, shape, dtype):
    f = detect_field(_as(_anatomy(shape, seed), dtype))
    assert f.kind == "none" and f.outside is None
    assert f.field_mask.all()
    assert f.valid_fraction > 0.99
    assert f.params["reason"]


def test_non_convex_body_outline_is_not_a_field():
    yy, xx = np.mgrid[:256, :256]
    blob = ((xx - 128) / 100) ** 2 + ((yy - 128) / 70) ** 2 + 0.3 * np.sin(3 * np.arctan2(yy - 128, xx - 128)) <= 1
    f = detect_field(_compose(blob, _anatomy(S, 2)))
    assert f.kind == "none"
    # the flat black background is still excluded as an empty plateau
    assert not (f.mask & ~ndimage.binary_dilation(blob, iterations=2)).any()


def test_two_separate_regions_are_not_one_field():
    yy, xx = np.mgrid[:256, :256]
    legs = (((xx - 80) / 45) ** 2 + ((yy - 140) / 120) ** 2 <= 1) | (((xx - 176) / 45) ** 2 + ((yy - 140) / 120) ** 2 <= 1)
    f = detect_field(_compose(legs, _anatomy(S, 4)))
    assert f.kind == "none" and "split" in f.params["reason"]
    assert f.mask[legs & (ndimage.distance_transform_edt(legs) > 3)].all()


# ------------------------------------------------------------------------------------------
# errors, settings, record, determinism


def test_errors_are_field_errors_with_clear_messages():
    with pytest.raises(FieldError, match="constant .*every pixel = 7.*no anatomy"):
        detect_field(np.full(S, 7, dtype=np.uint16))
    tiny = _circle(128, 128, 25)
    with pytest.raises(FieldError, match=r"field \(circle\) covers only 2\.\d % of the image \(< 10 %\)"):
        detect_field(_compose(tiny(S), _anatomy(S, 1)))
    bad = _anatomy(S, 1)
    bad[10, 10] = np.nan
    with pytest.raises(FieldError, match="NaN"):
        detect_field(bad)
    with pytest.raises(FieldError, match="2-D"):
        detect_field(np.zeros((3, 64, 64)))
    with pytest.raises(FieldError, match="real numbers"):
        detect_field(np.ones((64, 64), dtype=complex))
    assert issubclass(FieldError, XRayInputError) and issubclass(FieldError, ValueError)


def test_min_fraction_setting():
    truth_fn = _circle(128, 128, 60)  # 17 % of the image
    img = _compose(truth_fn(S), _anatomy(S, 2))
    assert detect_field(img).kind == "circle"
    with pytest.raises(FieldError, match=r"covers only 1\d\.\d % of the image \(< 30 %\)"):
        detect_field(img, FieldSettings(min_fraction=0.3))


@pytest.mark.parametrize("kwargs,words", [
    ({"margin_px": -1}, "margin_px: must be in"),
    ({"min_fraction": 1.5}, "min_fraction: must be in"),
    ({"level_tolerance": 0}, "level_tolerance: must be in"),
    ({"max_boundary_px": float("nan")}, "max_boundary_px: must be in"),
    ({"circle_min_inliers": "0.8"}, "circle_min_inliers: expected a number"),
    ({"overlay_min_px": 2.5}, "overlay_min_px: must be an integer"),
    ({"polygon_max_vertices": True}, "polygon_max_vertices: must be an integer"),
])
def test_bad_settings(kwargs, words):
    with pytest.raises(FieldError, match=words):
        FieldSettings(**kwargs)


def test_to_dict_is_json_and_complete():
    f = detect_field(_compose(_circle(127.5, 127.5, 110)(S), _anatomy(S, 1)))
    d = json.loads(json.dumps(f.to_dict()))
    assert set(d) == {"kind", "view", "outside", "params", "excluded", "valid_fraction", "field_fraction", "settings"}
    assert d["kind"] == "circle" and set(d["params"]) == {"centre_x", "centre_y", "radius"}
    assert d["settings"]["margin_px"] == 2.0
    assert d["valid_fraction"] == pytest.approx(f.mask.mean(), abs=1e-5)
    assert d["field_fraction"] == pytest.approx(f.field_mask.mean(), abs=1e-5)


def test_reproducible_and_input_untouched():
    truth = _regular_polygon(128, 128, 115, 6, 0.2)(S)
    img = _as(_compose(truth, _anatomy(S, 3), outside=0.05, out_noise=0.02), "u12")
    img[_glyphs(S, [("text", (90, 120), "kV 70")])] = 4095
    copy = img.copy()
    a, b = detect_field(img), detect_field(img)
    assert np.array_equal(img, copy)
    assert np.array_equal(a.mask, b.mask) and np.array_equal(a.field_mask, b.field_mask)
    assert a.to_dict() == b.to_dict()
    assert a.mask.dtype == bool and a.mask.shape == S


# ------------------------------------------------------------------------------------------
# linear displays: the anatomy within a few grey levels of one extreme


def _linear_display(truth, seed, bone_bright, leak=0.0):
    """A 10-bit linear (intensity, not log) display of a thick body: line integrals 3.5-6.5 in the
    field's upper three quarters (transmission 0.2-3 %: the anatomy within 30 of 1023 levels), air
    below; outside the field a painted black (``leak`` 0) or blades passing ``leak`` of the beam;
    bone-bright shows 1023 - I."""
    H, W = truth.shape
    line = 3.5 + 3.0 * _anatomy(truth.shape, seed, lo=0.0, hi=1.0)
    rows = np.arange(H)[:, None] * np.ones((1, W))
    air = 1.0 / (1.0 + np.exp(-(rows - 0.78 * H) / 2.0))  # a soft skin edge
    intensity = np.exp(-line * (1.0 - air))
    intensity = np.where(truth, intensity, leak * intensity)
    counts = np.round(1023 * intensity)
    return (1023 - counts if bone_bright else counts).astype(np.uint16)


@pytest.mark.parametrize("bone_bright,view", [(False, "log-dark"), (True, "log-bright")])
def test_linear_display_field_found_in_its_log_view(bone_bright, view):
    truth_fn = _regular_polygon(128, 120, 120, 4, 0.3)
    truth = truth_fn(S)
    img = _linear_display(truth, 5, bone_bright)
    f = detect_field(img)
    assert f.view == view and f.kind == "polygon"
    # the mask is of the image's own pixels; wrong pixels only at the blurred boundary, and the
    # truth's own quantisation puts a few anatomy pixels at the extreme (excluded as empty)
    wrong = (f.field_mask != truth) & (_boundary_distance(truth_fn, S) > 3.0)
    assert wrong.sum() == 0
    assert f.outside == ("white" if bone_bright else "black")
    assert f.to_dict()["view"] == view


def test_log_views_are_monotone_and_spread_the_extreme():
    img = np.array([[0, 1, 2, 4], [100, 500, 1022, 1023]], np.uint16)
    dark, bright = log_view(img, "log-dark"), log_view(img, "log-bright")
    assert np.all(np.diff(dark.ravel()) > 0) and np.all(np.diff(bright.ravel()) < 0)
    # next to its extreme a level is twice the last (log 2 apart); far from it they nearly merge
    assert dark[0, 1] - dark[0, 0] == pytest.approx(np.log(2)) and bright[1, 2] - bright[1, 3] == pytest.approx(np.log(2))
    assert dark[1, 3] - dark[1, 2] < 0.001
    with pytest.raises(FieldError, match="log view must be one of"):
        log_view(img, "log")
    with pytest.raises(FieldError, match="constant"):
        log_view(np.ones((4, 4)), "log-dark")


def test_linear_display_behind_leaky_blades_keeps_its_field():
    """Blades passing 0.3 % of the beam: outside, the air below the body leaks a few levels and the
    rest is black, two levels no single outside explains, so no collimation is fitted; the
    logarithmic view still keeps the anatomy (not refused) and leaves the black outside out."""
    truth = _regular_polygon(128, 120, 120, 4, 0.3)(S)
    f = detect_field(_linear_display(truth, 6, False, leak=0.003))
    assert f.view == "log-dark"
    assert f.mask[truth].mean() > 0.85
    assert f.mask[~truth].mean() < 0.5


def test_a_notched_circle_is_found_at_a_finer_detector_resolution():
    """The same notched field at 2x the pixels (512 px): a notch's mean depth in px grows with the
    resolution, and the notch limits (set at 256 px) grow with the image's side, so the circle is
    still found (before they scaled, 1024 px irises with clipped anatomy were kind ``none``)."""
    truth_fn = _circle(130, 124, 112)
    truth = truth_fn(S)
    img = _compose(truth, _notched(_anatomy(S, 21), truth, 0.0, 21, count=8))
    fine = _as(ndimage.zoom(img, 2, order=1), "u12")
    f = detect_field(fine)
    assert f.kind == "circle", f.params
    assert abs(f.params["radius"] - 2 * 112) <= 3.0  # 1.5 px at 256 px
    assert abs(f.field_mask.mean() - truth.mean()) < 0.01


# ------------------------------------------------------------------------------------------
# leaky blades and deep notches: the outside at two levels, a circle seen along part of its edge


def _leaky_iris(truth, seed, air_outside):
    """A round field over a body whose lower quarter is air (a soft skin edge at row 0.72 H): in the
    field anatomy in [0.25, 0.85] and the air clipped white (1.0); behind the blades the body's
    shadow clipped black (0.0) and the air's at ``air_outside`` (1.0: clipped too; less: a smooth
    grey, darker towards the edge as a heel effect would make it)."""
    H, W = truth.shape
    rows = np.arange(H)[:, None] * np.ones((1, W))
    air = 1.0 / (1.0 + np.exp(-(rows - 0.72 * H) / 1.5))
    inside = (1.0 - air) * _anatomy(truth.shape, seed) + air * 1.0
    cols = np.ones((H, 1)) * np.arange(W)[None, :]
    outside = air * air_outside * (1.0 - 0.1 * cols / W)
    return np.where(truth, inside, outside)


@pytest.mark.parametrize("air_outside", [1.0, 0.4])
def test_leaky_iris_with_the_air_behind_it_at_a_second_level(air_outside):
    """The air behind leaky blades is a second outside level (clipped white, or a smooth grey) that
    the field candidate runs into: no single outside level leaves a shape model (kind ``none``
    before step 1b); grown as a second level from the border, it leaves the circle (centre and
    radius within 1.5 px), and the field keeps no pixel of the air behind the blades."""
    truth_fn = _circle(128, 110, 100)
    truth = truth_fn(S)
    img = _as(_leaky_iris(truth, 31, air_outside), "u12")
    f = detect_field(img)
    assert f.kind == "circle", f.params
    assert f.params["outside_levels"] == 2
    cx, cy, r = truth_fn.circle
    p = f.params
    assert abs(p["centre_x"] - cx) <= 1.5 and abs(p["centre_y"] - cy) <= 1.5 and abs(p["radius"] - r) <= 1.5
    dist = _boundary_distance(truth_fn, S)
    assert ((f.field_mask != truth) & (dist > 3)).sum() == 0
    assert not (f.mask & ~truth).any()


def test_deeply_notched_circle_is_found_by_its_clean_arc():
    """Four discs of anatomy at the outside's level, 45 px in radius, on a 110 px circle's edge: the
    notches (about 14 px of area per boundary px, over the iris limits) leave about 60 % of the
    circumference clean. The circle is found from that arc (within 1.5 px; ``arc_cover`` recorded),
    the notches are excluded as empty plateaus, not cut from the field."""
    truth_fn = _circle(128, 128, 110)
    truth = truth_fn(S)
    img = _as(_compose(truth, _notched(_anatomy(S, 41), truth, 0.0, 41, count=4, radius=45)), "u12")
    f = detect_field(img)
    assert f.kind == "circle", f.params
    assert 0.5 <= f.params["arc_cover"] < 0.9 and f.params["notched"] > 4.0
    assert abs(f.params["radius"] - 110) <= 1.5
    assert ((f.field_mask != truth) & (_boundary_distance(truth_fn, S) > 3)).sum() == 0


def test_a_body_outline_on_air_is_not_a_notched_circle():
    """An open field: a round-ish body (an ellipse with lobes, not convex) on a flat black background
    and, beside it, a smaller second part. Neither the body's outline nor the two parts together
    cover half of any circle's circumference cleanly: kind ``none``."""
    yy, xx = np.mgrid[:256, :256]
    ang = np.arctan2(yy - 128, xx - 128)
    body = ((xx - 128) / 100) ** 2 + ((yy - 128) / 90) ** 2 + 0.25 * np.sin(4 * ang) <= 1
    f = detect_field(_compose(body, _anatomy(S, 43)))
    assert f.kind == "none", f.params
    legs = (((xx - 80) / 45) ** 2 + ((yy - 140) / 120) ** 2 <= 1) | (((xx - 176) / 45) ** 2 + ((yy - 140) / 120) ** 2 <= 1)
    f = detect_field(_compose(legs, _anatomy(S, 44)))
    assert f.kind == "none" and "split" in f.params["reason"]


def test_notched_shutter_polygon_is_found_one_sided():
    """A rotated square field notched by six discs of anatomy at the outside's level on its edges
    (no model within 0.5 px: kind ``none`` before the one-sided polygon): its hull is accepted, as
    its edges are followed by the candidate's boundary along most of their length (``edge_cover``
    >= 0.8) and it covers over a quarter of the image; the field within 3 px of the truth. The same
    field at a third of the area (under a quarter of the image: a part of a field is as likely) is
    not accepted one-sided."""
    truth_fn = _regular_polygon(128, 124, 130, 4, 0.35)
    truth = truth_fn(S)
    img = _as(_compose(truth, _notched(_anatomy(S, 51), truth, 0.0, 51, count=6, radius=12), blur=0.8), "u12")
    f = detect_field(img)
    assert f.kind == "polygon" and len(f.params["vertices"]) == 4, f.params
    assert f.params["edge_cover"] >= 0.8 and f.params["notched"] > 0.5
    assert ((f.field_mask != truth) & (_boundary_distance(truth_fn, S) > 3)).sum() == 0
    small = _regular_polygon(128, 124, 75, 4, 0.35)(S)
    g = detect_field(_as(_compose(small, _notched(_anatomy(S, 51), small, 0.0, 51, count=6, radius=12), blur=0.8), "u12"))
    assert small.mean() < 0.25 and "edge_cover" not in g.params


def test_a_one_sided_fit_leaving_too_little_is_dropped_not_refused(monkeypatch):
    """A field from a second outside level or a one-sided (notched) fit that leaves under
    ``min_fraction`` valid pixels (on a study frame: a region of air taken for the field) is
    dropped, and the image reads as without a fitted field; a clean fit that small still refuses."""
    import register.xray.field as field_module

    img = _as(_compose(_circle(128, 128, 100)(S), _anatomy(S, 61)), "u12")
    tiny = _circle(128, 128, 20)(S)

    def one_sided(med, out, s):
        return "circle", tiny, {"centre_x": 128.0, "centre_y": 128.0, "radius": 20.0, "arc_cover": 0.6}, ""

    monkeypatch.setattr(field_module, "_fit_outside", one_sided)
    f = detect_field(img)
    assert f.kind == "none" and f.view == "display" and f.field_mask.all()

    def clean(med, out, s):
        return "circle", tiny, {"centre_x": 128.0, "centre_y": 128.0, "radius": 20.0}, ""

    monkeypatch.setattr(field_module, "_fit_outside", clean)
    with pytest.raises(FieldError, match="covers only"):
        detect_field(img)


# ------------------------------------------------------------------------------------------
# raw (linear) frames: the shadow keeps the anatomy's texture, air is a bright plateau


def _raw_frame(shape, seed, collimator, *, air=True):
    """A raw detector signal I0 exp(-L): a body (an ellipse of line integrals 2-6 with texture) beside
    air (L = 0) when ``air``, Poisson-like noise, then the collimator (its transmission times the
    signal outside its field)."""
    rng = np.random.default_rng(seed)
    H, W = shape
    yy, xx = np.mgrid[:H, :W]
    tex = _anatomy(shape, seed, lo=2.0, hi=6.0, noise=0.0)
    if air:  # the body's edge: the path length grows from 0 at the skin as the square root of the depth
        r = np.hypot((yy - 0.55 * H) / (0.55 * H), (xx - 0.45 * W) / (0.5 * W))
        depth = np.clip(1.0 - r, 0.0, None)
        L = tex * np.sqrt(np.clip(depth / 0.25, 0.0, 1.0))
    else:
        L = tex
    signal = 65000.0 * np.exp(-L)
    signal = signal + rng.normal(size=shape) * np.sqrt(signal)
    return np.clip(collimator.apply(np.clip(signal, 1.0, None)), 0.1, None)


@pytest.mark.parametrize("shape_kw, kind", [
    (dict(shape="circle", radius=0.46), "circle"),
    (dict(shape="circle", radius=0.6, center=(0.45, 0.5)), "circle"),
    (dict(shape="rectangle", half_size=(0.38, 0.42), center=(0.52, 0.5)), ("rectangle", "polygon")),
    (dict(shape="iris-blades", radius=0.5, half_size=(0.4, 0.5)), ("iris-blades", "polygon")),  # a fine polygon fits too
])
@pytest.mark.parametrize("transmission", [0.02, 0.005])
def test_raw_frames_field_found_by_its_edge(shape_kw, kind, transmission):
    """A raw frame's collimator, its shadow textured and air beside the body: found by its edge
    (IoU with the truth >= 0.95: the 2 px margin costs ~3 % at 256 px), not by a level."""
    from sim.physics.display import Collimator

    col = Collimator(transmission=transmission, **shape_kw)
    for seed in range(3):
        img = _raw_frame((256, 256), seed, col)
        truth = col.mask(256, 256)
        found = detect_field(img, raw=True)
        assert found.kind in ((kind,) if isinstance(kind, str) else kind), (seed, found.params)
        iou = (found.field_mask & truth).sum() / (found.field_mask | truth).sum()
        assert iou >= 0.95 and not (found.field_mask & ~truth).any(), (seed, iou)
        assert found.view == "raw" and found.outside == "black"


def test_raw_frames_without_collimation_keep_their_air():
    """No steep closed edge: the whole frame is the field (air included), not the body cut out as a
    'field' beside a painted-looking bright outside."""
    from sim.physics.display import Collimator

    for seed in range(3):
        img = _raw_frame((256, 256), seed, Collimator(shape="none"))
        found = detect_field(img, raw=True)
        assert found.kind == "none" and found.field_mask.all(), found.params
        assert "no collimator" in found.params["reason"]


def test_raw_frames_must_not_be_negative():
    img = np.linspace(-1.0, 1.0, 64 * 64).reshape(64, 64)
    with pytest.raises(FieldError, match="not negative"):
        detect_field(img, raw=True)


def test_where_no_model_fits_the_image_its_log_views_are_tried(monkeypatch):
    """The image as stored fits no model (kind ``"none"``) though it leaves enough field: a fitted
    model of a logarithmic view replaces it (a linear display behind a leaky iris), a ``"none"``
    of the log views does not (the image's own result is kept)."""
    import register.xray.field as field_module

    truth = _circle(128, 128, 100)(S)
    img = _as(_compose(truth, _anatomy(S, 3)), "u12")
    real = field_module._detect
    seen = []

    def display_fits_nothing(view, s):
        found = real(view, s)
        seen.append(found.kind)
        if len(seen) == 1:  # the image as stored
            return dataclasses.replace(found, kind="none", params={"reason": "stand-in"},
                                       field_mask=np.ones_like(found.field_mask))
        return found

    monkeypatch.setattr(field_module, "_detect", display_fits_nothing)
    f = detect_field(img)
    assert f.kind == "circle" and f.view in ("log-dark", "log-bright") and len(seen) == 2

    seen.clear()

    def nothing_fits(view, s):
        found = real(view, s)
        seen.append(found.kind)
        return dataclasses.replace(found, kind="none", params={"reason": "stand-in"})

    monkeypatch.setattr(field_module, "_detect", nothing_fits)
    f = detect_field(img)
    assert f.kind == "none" and f.view == "display" and len(seen) == 3


def test_a_small_field_gives_way_to_a_log_views_field_around_it(monkeypatch):
    """A field fitted to under 30 % of the image as stored (the air inside the field, the body read
    as outside) is replaced by a log view's fitted field that holds it and is 1.5 times larger; a
    log view's field elsewhere, or one not larger, leaves it as it is."""
    import register.xray.field as field_module

    truth = _circle(128, 128, 100)(S)
    img = _as(_compose(truth, _anatomy(S, 3)), "u12")
    real = field_module._detect
    small = np.zeros(S, bool)
    small[150:200, 100:160] = True  # inside the circle: 3000 px, 5 % of the image
    elsewhere = np.zeros(S, bool)
    elsewhere[:, :100] = True  # 39 % of the image, holding none of it
    calls = []

    def display_small(log_field):
        def detect(view, s):
            found = real(view, s)
            calls.append(found.kind)
            if len(calls) == 1:  # the image as stored: a polygon fitted to the small region
                return dataclasses.replace(found, kind="polygon", field_mask=small, mask=small)
            return found if log_field is None else dataclasses.replace(found, field_mask=log_field(found))
        return detect

    monkeypatch.setattr(field_module, "_detect", display_small(None))
    f = detect_field(img)
    assert f.kind == "circle" and f.view in ("log-dark", "log-bright") and f.field_mask[small].all()
    for log_field in (lambda found: elsewhere, lambda found: small | np.roll(small, 20, axis=0)):  # 1.4x: not larger
        calls.clear()
        monkeypatch.setattr(field_module, "_detect", display_small(log_field))
        f = detect_field(img)
        assert f.view == "display" and np.array_equal(f.field_mask, small) and len(calls) == 3


def test_tools_left_out_of_a_field_keep_its_counts_disjoint():
    """Field.without_tools: the tools inside the field leave the mask; ``excluded["tools"]`` counts
    only those still valid (not also a plateau's), tools outside the field are dropped, and a mask
    of another shape is named."""
    img = np.full((64, 64), 100.0) + np.random.default_rng(0).normal(0, 3, (64, 64))
    img[:, :8] = 0.0  # a black shutter on the left
    img[20:30, 30:40] = img.max() + 50  # a saturated plateau
    found = detect_field(img)
    tools = np.zeros((64, 64), bool)
    tools[25:35, 35:45] = True  # a quarter of it on the plateau
    tools[40:42, 0:20] = True  # partly outside the field
    out = found.without_tools(tools)
    assert not (out.mask & tools).any() and not (out.tools & ~found.field_mask).any()
    assert out.excluded["tools"] == int((tools & found.mask).sum())
    assert out.excluded["tools"] < int((tools & found.field_mask).sum())  # the plateau's quarter counted once
    assert (out.mask | (tools & found.mask)).sum() == found.mask.sum()
    assert out.to_dict()["excluded"]["tools"] == out.excluded["tools"]
    with pytest.raises(FieldError, match="bool mask"):
        found.without_tools(tools[:10])


def test_attenuating_pieces_keeps_what_attenuates_more_than_most_of_the_field():
    """attenuating_pieces: of two detected pieces on an attenuation-bright image whose values rise
    left to right, the one at the right (rank 0.94 of the valid pixels) is kept and the one at the
    left (rank 0.06: an air edge, say) is given back; the rank bound itself (0.5) splits a piece at
    the field's median; empty tools, a wrong shape and a rank outside [0, 1) are handled."""
    from register.xray.field import TOOL_MIN_ATTENUATION_RANK, attenuating_pieces

    img = np.tile(np.linspace(0.0, 1.0, 50), (40, 1))
    tools = np.zeros((40, 50), bool)
    tools[10:14, 2:4] = True   # median column 2.5: rank 0.06
    tools[20:24, 46:48] = True  # rank 0.94
    kept = attenuating_pieces(tools, img, ~tools)
    assert kept[20:24, 46:48].all() and not kept[10:14, 2:4].any() and kept.sum() == 8
    assert TOOL_MIN_ATTENUATION_RANK == 0.5
    mid = np.zeros((40, 50), bool)
    mid[30:32, 26:28] = True  # just above the median column
    assert attenuating_pieces(mid, img, ~mid).any() and not attenuating_pieces(mid, img, ~mid, min_rank=0.6).any()
    assert not attenuating_pieces(np.zeros((40, 50), bool), img, np.ones((40, 50), bool)).any()
    with pytest.raises(FieldError, match="one shape"):
        attenuating_pieces(tools[:10], img, ~tools)
    with pytest.raises(FieldError, match="min_rank"):
        attenuating_pieces(tools, img, ~tools, min_rank=1.0)
