"""Preprocessing steps against known truth: frames found by the field step and cropped to, salt
noise, -log of a known I0 exp(-L), percentile mapping, the intensity step; the pipeline record and
the geometry of a cropped image."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import ndimage

from register.xray.preprocess import (
    STEPS,
    DEFAULT_STEPS,
    Crop,
    Field,
    Intensity,
    Invert,
    LogCorrect,
    Median,
    Normalize,
    Pipeline,
    PreprocessError,
    crop_box,
    cropped_geometry,
)
from sim.projection.geometry import CArmGeometry, backproject_pixel
from tests.conftest import shared_file


def _anatomy(h=120, w=150, seed=0):
    """A structured image (smoothed noise, std ~ 40) standing in for anatomy, values ~ 500."""
    rng = np.random.default_rng(seed)
    f = ndimage.gaussian_filter(rng.normal(size=(h, w)), 4.0)
    return 500.0 + 40.0 * f / f.std()


def _framed(top=12, bottom=0, left=20, right=7, seed=0):
    """Anatomy inside a frame of known widths: a constant top border (level 0), a noisy collimator
    band on the left (level 900, noise std 1), a constant right band (level 900)."""
    img = _anatomy(seed=seed)
    h, w = img.shape
    rng = np.random.default_rng(seed + 1)
    img[:top] = 0.0
    if bottom:
        img[h - bottom:] = 0.0
    img[:, :left] = 900.0 + rng.normal(0.0, 1.0, (h, left))
    img[:, w - right:] = 900.0
    return img, (top, h - bottom, left, w - right)


# --------------------------------------------------------------------------- Field and Crop


def _shutters(top, bottom, left, right, level, noise, seed=0):
    """Anatomy inside rectangular shutters of one level (a vendor's constant or a noisy shadow)."""
    img = _anatomy(seed=seed)
    h, w = img.shape
    rng = np.random.default_rng(seed + 1)
    out = level + noise * rng.normal(size=img.shape)
    out[top:h - bottom, left:w - right] = img[top:h - bottom, left:w - right]
    return out, (top, h - bottom, left, w - right)


@pytest.mark.parametrize("widths, level, noise", [((12, 0, 20, 7), 0.0, 0.0), ((0, 9, 0, 15), 900.0, 0.0),
                                                  ((30, 25, 6, 5), 0.0, 1.0)])
def test_field_then_crop_finds_shutters_of_known_width(widths, level, noise):
    """Shutters (black, white, or a noisy shadow) around the anatomy are a rectangular field; the
    crop follows it."""
    img, truth = _shutters(*widths, level, noise)
    out, mask, rec = Pipeline([Field(margin_px=0.0), Crop(margin_px=0)]).apply(img)
    assert rec[0]["measured"]["kind"] == "rectangle"
    box = rec[1]["measured"]["crop_box"]
    assert np.abs(np.array(box) - np.array(truth)).max() <= 2, (box, truth)
    assert out.shape == mask.shape == (box[1] - box[0], box[3] - box[2])
    np.testing.assert_array_equal(out, img[box[0]:box[1], box[2]:box[3]].astype(np.float32))


def test_crop_follows_the_mask_and_leaves_an_image_without_one_alone():
    img = _anatomy()
    assert Pipeline([Crop()]).apply(img)[2][0]["measured"]["crop_box"] == [0, 120, 0, 150]
    mask = np.zeros(img.shape, bool)
    mask[30:61, 40:101] = True
    out, m, rec = Pipeline([Crop(margin_px=3)]).apply(img, mask)
    assert rec[0]["measured"]["crop_box"] == [27, 64, 37, 104]
    assert m.shape == out.shape and m.sum() == mask.sum()


def test_field_finds_a_frame_added_to_a_real_radiograph():
    from register.xray.io import load_xray

    x = load_xray(shared_file("xray/paediatric_ap_pelvis/dicoms/331_DDH_10.dcm")).pixels
    padded = np.pad(x, ((14, 6), (25, 0)), constant_values=255.0)  # white collimator shadow top/bottom/left
    _, _, rec = Pipeline([Field(margin_px=0.0), Crop(margin_px=0)]).apply(padded)
    box = rec[1]["measured"]["crop_box"]
    assert np.abs(np.array(box) - [14, 14 + 331, 25, 25 + 331]).max() <= 3, box


def test_intensity_step_applies_what_it_decides_and_records_why():
    """A bone-dark noisy frame tagged as raw (FOR PROCESSING) is log-corrected: the result is the
    line integral of the truth up to noise."""
    rng = np.random.default_rng(0)
    L = 1.0 + (_anatomy() - 500.0) / 200.0
    raw = rng.poisson(5000.0 * np.exp(-L)).astype(np.float64)
    tags = {"PresentationIntentType": "FOR PROCESSING", "Modality": "DX"}
    out, _, rec = Pipeline([Intensity(tags=tags)]).apply(raw)
    m = rec[0]["measured"]
    assert (m["scale"], m["polarity"], m["steps"]) == ("linear", "bone-dark", ["log"])
    assert m["scale_source"] == "DICOM PresentationIntentType" and m["evidence"]
    assert [a["step"] for a in m["applied"]] == ["log"]
    assert np.corrcoef(out.ravel(), L.ravel())[0, 1] > 0.99
    assert rec[0]["params"]["scale"] == "auto" and json.loads(json.dumps(rec)) == rec


def test_default_steps_are_the_register_default():
    assert Pipeline.from_names(DEFAULT_STEPS).names == ["field", "median", "intensity", "normalize", "crop"]


def test_cropped_geometry_keeps_each_pixel_on_its_ray():
    img, _ = _framed(12, 0, 20, 7)
    geom = CArmGeometry(1020.0, 700.0, img.shape[0], img.shape[1], 0.5, cx=70.3, cy=61.0)
    out, _, rec = Pipeline.from_names(["field", "median", "crop"]).apply(img)
    r0, r1, c0, c1 = crop_box(rec, img.shape)
    g = cropped_geometry(geom, rec)
    assert (g.height, g.width) == out.shape == (r1 - r0, c1 - c0)
    i, j = np.meshgrid(np.arange(g.height), np.arange(g.width), indexing="ij")
    # independent truth: the output pixel (i, j) is input pixel (i + r0, j + c0), so the same ray
    np.testing.assert_allclose(backproject_pixel(g, j, i), backproject_pixel(geom, j + c0, i + r0), atol=1e-12)


def test_successive_crops_compose():
    rec = [{"step": "crop", "measured": {"crop_box": [2, 50, 3, 40]}},
           {"step": "crop", "measured": {"crop_box": [1, 10, 4, 20]}}]
    assert crop_box(rec, (60, 60)) == (3, 12, 7, 23)


# --------------------------------------------------------------------------- the other steps


def test_median_removes_isolated_salt_noise():
    i, j = np.mgrid[0:40, 0:50].astype(np.float64)
    clean = 3.0 * i + 2.0 * j  # a ramp: a 3x3 median moves it by at most |3| + |2|
    noisy = clean.copy()
    salt = (i % 5 == 2) & (j % 7 == 3)  # isolated: one per 3 x 3 window at most
    noisy[salt] = 1e4
    out, _, rec = Pipeline([Median(3)]).apply(noisy)
    assert np.abs(noisy - clean).max() > 9000
    assert np.abs(out - clean).max() <= 5.0 + 1e-9
    assert rec[0]["measured"]["changed_fraction"] > 0


def test_log_correct_recovers_line_integrals_with_a_given_i0():
    rng = np.random.default_rng(3)
    L = rng.uniform(0.0, 5.0, (30, 40))
    out, _, rec = Pipeline([LogCorrect(i0=3000.0)]).apply(3000.0 * np.exp(-L))
    assert np.abs(out - L).max() < 1e-5  # float32 output of values up to 5: ~3e-7
    assert rec[0]["measured"]["i0"] == 3000.0 and rec[0]["measured"]["i0_source"] == "given"


def test_log_correct_takes_i0_from_the_unattenuated_region():
    rng = np.random.default_rng(4)
    L = rng.uniform(0.2, 4.0, (40, 40))
    L[:, :8] = 0.0  # 20 % direct beam: the 99.5th percentile is I0 itself
    out, _, rec = Pipeline([LogCorrect()]).apply(1234.5 * np.exp(-L))
    assert rec[0]["measured"]["i0"] == pytest.approx(1234.5, rel=1e-12)
    assert np.abs(out - L).max() < 1e-5


def test_log_correct_clips_zeros_and_refuses_non_positive_images():
    img = np.full((5, 5), 100.0)
    img[2, 2] = 0.0
    out, _, rec = Pipeline([LogCorrect(i0=100.0, floor_frac=1e-3)]).apply(img)
    assert rec[0]["measured"]["clipped_pixels"] == 1
    assert out[2, 2] == pytest.approx(-np.log(1e-3), rel=1e-6)
    with pytest.raises(PreprocessError, match="positive"):
        Pipeline([LogCorrect()]).apply(-np.ones((5, 5)))


def test_normalize_maps_percentiles_to_zero_and_one():
    x = np.arange(100 * 101, dtype=np.float64).reshape(100, 101)  # values 0..N-1
    n = x.size
    lo, hi = 0.01 * (n - 1), 0.99 * (n - 1)  # linear-interpolated percentiles of 0..N-1
    out, _, rec = Pipeline([Normalize(1, 99)]).apply(x)
    m = rec[0]["measured"]
    assert m["low"] == pytest.approx(lo, rel=1e-12) and m["high"] == pytest.approx(hi, rel=1e-12)
    np.testing.assert_allclose(out, np.clip((x - lo) / (hi - lo), 0, 1), atol=1e-6)
    assert out.min() == 0.0 and out.max() == 1.0


def test_normalize_uses_only_valid_pixels():
    x = np.tile(np.linspace(10.0, 20.0, 50), (20, 1))
    mask = np.ones_like(x, dtype=bool)
    x[:, :5] = 1e6  # outliers outside the mask
    mask[:, :5] = False
    out, m, rec = Pipeline([Normalize(0, 100)]).apply(x, mask)
    assert rec[0]["measured"]["low"] == pytest.approx(10.0 + 10.0 * 5 / 49, rel=1e-12)
    assert rec[0]["measured"]["high"] == pytest.approx(20.0, rel=1e-12)
    assert m is not mask and np.array_equal(m, mask)
    with pytest.raises(PreprocessError, match="flat"):
        Pipeline([Normalize()]).apply(np.ones((4, 4)))


def test_invert_reverses_within_the_same_range():
    x = np.random.default_rng(5).uniform(3.0, 8.0, (10, 10))
    out, _, rec = Pipeline([Invert()]).apply(x)
    np.testing.assert_allclose(out, x.max() + x.min() - x, atol=1e-5)
    np.testing.assert_allclose(Pipeline([Invert(), Invert()]).apply(x)[0], x, atol=1e-5)


# --------------------------------------------------------------------------------- Pipeline


def test_pipeline_record_is_json_and_lists_every_step_with_its_measurements():
    img, truth = _framed(12, 0, 20, 7)
    transmitted = 2000.0 * np.exp(-img / 1000.0)  # a positive transmission-like image
    mask = np.ones(img.shape, dtype=bool)
    p = Pipeline.from_names(["field", "median", "log", "normalize", "invert", "crop"])
    out, m, rec = p.apply(transmitted, mask)
    back = json.loads(json.dumps(rec))
    assert back == rec
    assert [r["step"] for r in rec] == ["field", "median", "log", "normalize", "invert", "crop"] == p.names
    assert np.abs(np.array(rec[5]["measured"]["crop_box"]) - truth).max() <= 4  # the 2 px field margin
    assert rec[0]["params"] == {"margin_px": 2.0} and rec[0]["measured"]["kind"] == "rectangle"
    assert rec[2]["measured"]["i0_source"] == "percentile" and rec[2]["measured"]["i0"] > 0
    assert {"low", "high"} <= set(rec[3]["measured"])
    assert out.dtype == np.float32 and out.shape == m.shape and 0.0 <= out.min() and out.max() <= 1.0


def test_unknown_step_names_and_bad_parameters_are_errors():
    with pytest.raises(PreprocessError, match="valid steps") as e:
        Pipeline.from_names(["field", "sharpen"])
    assert "sharpen" in str(e.value) and all(n in str(e.value) for n in STEPS)
    with pytest.raises(PreprocessError, match="odd"):
        Median(4)
    with pytest.raises(PreprocessError, match="low_pct"):
        Normalize(50, 10)
    with pytest.raises(PreprocessError, match="shape"):
        Pipeline([]).apply(np.zeros(5))
    with pytest.raises(PreprocessError, match="NaN"):
        Pipeline([]).apply(np.full((3, 3), np.nan))


def test_intensity_step_records_a_tone_curve_for_display_images_only():
    """A display image (gamma 2.6 over the log) with a CT reference gets the tone curve (the
    reference's line-integral quantiles in the field) in its record and keeps its values; the toned
    image made from it (register.xray.prepare.toned_image) is the line integral again (correlation >
    0.99, where the display is not); ``tone="off"``, a log image or no reference get no curve. A bad
    tone name is refused."""
    from register.xray.intensity import TONE_LEVELS, PolarityReference
    from register.xray.prepare import toned_image

    L = 1.0 + (_anatomy() - 500.0) / 200.0
    shown = ((L - L.min()) / np.ptp(L)) ** 2.6
    ref = PolarityReference(drrs=np.stack([np.roll(L, s, axis=1) for s in (-8, 8)]), resample=lambda im, m: (im, m))
    tags = {"Modality": "DX"}  # a radiograph for presentation: display, bone bright
    out, _, rec = Pipeline([Intensity(tags=tags, reference=ref)]).apply(shown)
    m = rec[0]["measured"]
    assert m["scale"] == "display" and m["steps"] == [] and m["tone"].startswith("ct")
    assert len(m["tone_curve"]) == TONE_LEVELS and json.loads(json.dumps(rec)) == rec
    np.testing.assert_allclose(out, shown.astype(np.float32))  # the image is left as decided
    toned = toned_image(out.astype(np.float64), None, m["tone_curve"])
    assert 0.0 <= toned.min() and toned.max() <= 1.0
    assert np.corrcoef(toned.ravel(), L.ravel())[0, 1] > 0.99 > np.corrcoef(shown.ravel(), L.ravel())[0, 1]
    assert toned_image(out, None, None) is None
    for kw in ({"tone": "off"}, {"scale": "log"}, {"reference": None}):
        _, _, rec2 = Pipeline([Intensity(tags=tags, **{"reference": ref, **kw})]).apply(shown)
        assert "tone_curve" not in rec2[0]["measured"]
    with pytest.raises(PreprocessError, match="tone"):
        Intensity(tone="histogram")
