"""Preprocessing steps against known truth: border widths, salt noise, -log of a known I0 exp(-L),
percentile mapping; the pipeline record and the geometry of a cropped image."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import ndimage

from register.preprocess import (
    STEPS,
    CropBorder,
    Invert,
    LogCorrect,
    Median,
    Normalize,
    Pipeline,
    PreprocessError,
    crop_box,
    cropped_geometry,
)
from sim.geometry import CArmGeometry, backproject_pixel
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


# -------------------------------------------------------------------------------- CropBorder


@pytest.mark.parametrize("widths", [(12, 0, 20, 7), (0, 9, 0, 15), (30, 25, 3, 1)])
def test_crop_border_finds_a_frame_of_known_width(widths):
    img, truth = _framed(*widths)
    out, mask, rec = Pipeline([CropBorder()]).apply(img)
    box = rec[0]["measured"]["crop_box"]
    assert np.abs(np.array(box) - np.array(truth)).max() <= 1, (box, truth)
    assert out.shape == (box[1] - box[0], box[3] - box[2]) and mask is None
    np.testing.assert_array_equal(out, img[box[0]:box[1], box[2]:box[3]].astype(np.float32))


def test_crop_border_leaves_an_image_without_border_alone():
    img = _anatomy()
    _, _, rec = Pipeline([CropBorder()]).apply(img)
    assert rec[0]["measured"]["crop_box"] == [0, 120, 0, 150]


def test_crop_border_finds_a_frame_added_to_a_real_radiograph():
    from register.xray_io import load_xray

    x = load_xray(shared_file("xray/paediatric_ap_pelvis/dicoms/331_DDH_10.dcm")).pixels
    assert Pipeline([CropBorder()]).apply(x)[2][0]["measured"]["crop_box"] == [0, 331, 0, 331]  # already tight
    padded = np.pad(x, ((14, 6), (25, 0)), constant_values=255.0)  # white collimator shadow top/bottom/left
    box = Pipeline([CropBorder()]).apply(padded)[2][0]["measured"]["crop_box"]
    assert np.abs(np.array(box) - [14, 14 + 331, 25, 25 + 331]).max() <= 1, box


def test_cropped_geometry_keeps_each_pixel_on_its_ray():
    img, _ = _framed(12, 0, 20, 7)
    geom = CArmGeometry(1020.0, 700.0, img.shape[0], img.shape[1], 0.5, cx=70.3, cy=61.0)
    out, _, rec = Pipeline.from_names(["median", "crop"]).apply(img)
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
    p = Pipeline.from_names(["crop", "median", "log", "normalize", "invert"])
    out, m, rec = p.apply(transmitted, mask)
    back = json.loads(json.dumps(rec))
    assert back == rec
    assert [r["step"] for r in rec] == ["crop", "median", "log", "normalize", "invert"] == p.names
    assert np.abs(np.array(rec[0]["measured"]["crop_box"]) - truth).max() <= 1
    assert rec[0]["params"] == {"std_frac": 0.1, "max_frac": 0.4}
    assert rec[2]["measured"]["i0_source"] == "percentile" and rec[2]["measured"]["i0"] > 0
    assert {"low", "high"} <= set(rec[3]["measured"])
    assert out.dtype == np.float32 and out.shape == m.shape and 0.0 <= out.min() and out.max() <= 1.0


def test_unknown_step_names_and_bad_parameters_are_errors():
    with pytest.raises(PreprocessError, match="valid steps") as e:
        Pipeline.from_names(["crop", "sharpen"])
    assert "sharpen" in str(e.value) and all(n in str(e.value) for n in STEPS)
    with pytest.raises(PreprocessError, match="odd"):
        Median(4)
    with pytest.raises(PreprocessError, match="low_pct"):
        Normalize(50, 10)
    with pytest.raises(PreprocessError, match="shape"):
        Pipeline([]).apply(np.zeros(5))
    with pytest.raises(PreprocessError, match="NaN"):
        Pipeline([]).apply(np.full((3, 3), np.nan))
