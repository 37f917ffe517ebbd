"""sim.prepare's steps, on a NumPy image and on a torch batch, against closed forms and against each other."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from sim import prepare
from sim.prepare import crop_to_field, gather2d, nearest_source, resize_boxes

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _case(seed: int, shape=(23, 31)):
    rng = np.random.default_rng(seed)
    image = rng.normal(5.0, 2.0, shape)
    mask = rng.random(shape) < 0.6
    return image, mask


def test_field_values_are_the_masked_pixels_or_all():
    image, mask = _case(0)
    np.testing.assert_array_equal(prepare.field_values(image, mask), image[mask])
    np.testing.assert_array_equal(prepare.field_values(image, None), image.ravel())


@pytest.mark.parametrize("masked", [True, False])
def test_invert_reverses_the_field_range_and_is_an_involution(masked):
    image, mask = _case(1)
    mask = mask if masked else None
    out, mn, mx = prepare.invert(image, mask)
    v = prepare.field_values(image, mask)
    assert (mn, mx) == (v.min(), v.max())
    np.testing.assert_allclose(out, mx + mn - image, rtol=0, atol=0)
    w = prepare.field_values(out, mask)
    assert w.min() == pytest.approx(mn) and w.max() == pytest.approx(mx)  # the range is kept
    back, _, _ = prepare.invert(out, mask)
    np.testing.assert_allclose(back, image, atol=1e-12)


def test_log_correct_is_minus_log_of_the_transmission():
    L = np.linspace(0.0, 6.0, 50).reshape(5, 10)
    i0 = 3000.0
    intensity = i0 * np.exp(-L)
    assert prepare.i0_percentile(intensity, None, 100.0) == pytest.approx(i0)
    np.testing.assert_allclose(prepare.log_correct(intensity, i0), L, atol=1e-12)
    # below floor_frac * I0 the pixels are clipped to it: -ln(floor_frac)
    out = prepare.log_correct(np.array([0.0, -5.0, 1e-9]), 1.0, floor_frac=1e-6)
    np.testing.assert_allclose(out, -np.log(1e-6))


def test_field_box_is_the_bounding_box_with_a_clipped_margin():
    mask = np.zeros((20, 30), bool)
    mask[4, 7] = mask[11, 25] = True
    assert prepare.field_box(mask) == (4, 12, 7, 26)
    assert prepare.field_box(mask, 3) == (1, 15, 4, 29)
    assert prepare.field_box(mask, 10) == (0, 20, 0, 30)


@pytest.mark.parametrize("masked", [True, False])
def test_normalize_maps_the_percentiles_to_0_and_1_and_clips(masked):
    image, mask = _case(2)
    mask = mask if masked else None
    lo, hi = prepare.percentile_bounds(image, mask, 5.0, 95.0)
    v = prepare.field_values(image, mask)
    assert (lo, hi) == (np.percentile(v, 5.0), np.percentile(v, 95.0))
    out = prepare.normalize(image, lo, hi)
    assert out.min() == 0.0 and out.max() == 1.0
    o = prepare.field_values(out, mask)
    assert np.mean(o == 0.0) == pytest.approx(np.mean(v <= lo)) and np.mean(o == 1.0) == pytest.approx(np.mean(v >= hi))
    inside = (image > lo) & (image < hi)
    np.testing.assert_allclose(out[inside], (image[inside] - lo) / (hi - lo), atol=1e-15)


def test_masked_fill_puts_the_field_mean_outside():
    image, mask = _case(3)
    out = prepare.masked_fill(image.astype(np.float32), mask)
    assert out.dtype == np.float64
    np.testing.assert_array_equal(out[mask], image.astype(np.float32)[mask])
    np.testing.assert_allclose(out[~mask], image.astype(np.float32)[mask].astype(np.float64).mean())
    np.testing.assert_array_equal(prepare.masked_fill(image, None), image)
    np.testing.assert_array_equal(prepare.masked_fill(image, np.zeros_like(mask)), 0.0)


def test_crop_to_field_of_the_whole_image_is_the_image_and_a_box_is_interpolate():
    image, _ = _case(4, (16, 12))
    whole = np.ones((16, 12), bool)
    same, same_m = crop_to_field((image.astype(np.float32),), whole)
    assert same.dtype == np.float64 and same_m is whole
    np.testing.assert_array_equal(same, image.astype(np.float32))
    field = np.zeros((16, 12), bool)
    field[2:10, 3:9] = True
    field[5, 5] = False  # a hole, resampled by nearest
    got, got_m = crop_to_field((image,), field)
    assert prepare.field_box(field) == (2, 10, 3, 9)
    crop = torch.from_numpy(image[2:10, 3:9].astype(np.float32))[None, None]
    ref = F.interpolate(crop, size=(16, 12), mode="bilinear", align_corners=False)[0, 0].double().numpy()
    assert got.dtype == np.float64 and got.shape == (16, 12)
    np.testing.assert_array_equal(got, ref)
    # nearest upsampling by 2 repeats each pixel of the field's crop
    np.testing.assert_array_equal(got_m, np.repeat(np.repeat(field[2:10, 3:9], 2, 0), 2, 1))
    kept, kept_m = crop_to_field((image,), field, crop=False)
    np.testing.assert_array_equal(kept, image) and np.testing.assert_array_equal(kept_m, field)


def test_a_flat_image_normalizes_to_0():
    flat = prepare.normalize(np.full((3, 4), 2.0), 2.0, 2.0)
    assert flat.dtype == np.float64 and not flat.any()
    flat_t = prepare.normalize(torch.ones(2, 4, 4, dtype=torch.float64), *prepare.percentile_bounds(
        torch.ones(2, 4, 4, dtype=torch.float64), torch.ones(2, 4, 4, dtype=torch.bool), 1.0, 99.0))
    assert torch.equal(flat_t, torch.zeros(2, 4, 4, dtype=torch.float64))  # equal percentiles: 0


def _batch(seed: int, b=5, h=19, w=27):
    rng = np.random.default_rng(seed)
    x = rng.normal(2.0, 1.0, (b, h, w))
    m = rng.random((b, h, w)) < rng.uniform(0.1, 0.9, (b, 1, 1))
    m[:, 3, 4] = True
    return x, m


def test_a_batch_gets_each_image_s_numpy_steps():
    x, m = _batch(5)
    xt, mt = torch.from_numpy(x), torch.from_numpy(m)
    which = torch.tensor([True, False, True, True, False])
    inv, lo, hi = prepare.invert(xt, mt, which)
    for i in range(len(x)):
        ref, ref_lo, ref_hi = prepare.invert(x[i], m[i], bool(which[i]))
        np.testing.assert_array_equal(inv[i].numpy(), ref)
        assert (float(lo[i]), float(hi[i])) == (ref_lo, ref_hi)
    boxes = torch.stack(prepare.field_box(mt), 1).numpy()
    assert [tuple(b) for b in boxes] == [prepare.field_box(m[i]) for i in range(len(m))]
    margin = torch.stack(prepare.field_box(mt, 4), 1).numpy()
    assert [tuple(b) for b in margin] == [prepare.field_box(m[i], 4) for i in range(len(m))]
    norm = prepare.normalize(xt, *prepare.percentile_bounds(xt, mt, 2.0, 90.0)).numpy()
    fill = prepare.masked_fill(xt, mt).numpy()
    for i in range(len(x)):
        lo, hi = prepare.percentile_bounds(x[i], m[i], 2.0, 90.0)
        np.testing.assert_allclose(norm[i], prepare.normalize(x[i], lo, hi), atol=1e-12)
        np.testing.assert_allclose(fill[i], prepare.masked_fill(x[i], m[i]), atol=1e-12)
    empty = mt.clone()
    empty[1] = False
    assert torch.equal(prepare.masked_fill(xt, empty)[1], torch.zeros_like(xt[1]))  # as NumPy: an empty field fills 0


def test_crop_to_field_of_a_batch_equals_each_image_s():
    x, m = _batch(6)
    m[0] = True  # a box that is the whole image: left as it is
    xt, mt = torch.from_numpy(x), torch.from_numpy(m)
    got, got_m = crop_to_field((xt,), mt)
    assert got.dtype == torch.float64
    for i in range(len(x)):
        ref, ref_m = crop_to_field((x[i],), m[i])
        np.testing.assert_allclose(got[i].numpy(), ref, atol=1e-5)
        np.testing.assert_array_equal(got_m[i].numpy(), ref_m)
    np.testing.assert_array_equal(got[0].numpy(), x[0])
    same, same_m = crop_to_field((xt,), mt, crop=False)
    assert torch.equal(same, xt) and torch.equal(same_m, mt)


@pytest.mark.parametrize("size", [(64, 64), (48, 80)], ids=["64x64", "48x80"])
def test_box_resampling_equals_interpolate_on_the_crop(size):
    h, w = size
    rng = np.random.default_rng(0)
    n = 40
    r0, c0 = rng.integers(0, h, n), rng.integers(0, w, n)
    r1, c1 = r0 + 1 + rng.integers(0, h - r0), c0 + 1 + rng.integers(0, w - c0)
    x = torch.from_numpy(rng.random((n, h, w)).astype(np.float32))
    mask = torch.from_numpy(rng.random((n, h, w)) < 0.5)
    box = tuple(torch.from_numpy(a) for a in (r0, r1, c0, c1))
    got = resize_boxes(x, box, size)
    rows = nearest_source(box[1] - box[0], h) + box[0][:, None]
    cols = nearest_source(box[3] - box[2], w) + box[2][:, None]
    got_mask = gather2d(mask, rows, cols)
    for i in range(n):
        crop = x[i, r0[i]:r1[i], c0[i]:c1[i]][None, None]
        ref = F.interpolate(crop, size=size, mode="bilinear", align_corners=False)[0, 0]
        assert (got[i] - ref).abs().max() <= 1e-6
        ref_mask = F.interpolate(mask[i, r0[i]:r1[i], c0[i]:c1[i]][None, None].float(), size=size,
                                 mode="nearest")[0, 0] > 0.5
        assert torch.equal(got_mask[i], ref_mask)


def test_checked_image_takes_a_finite_numeric_2d_image_and_names_what_is_wrong():
    from sim.prepare import checked_image

    class Bad(ValueError):
        pass

    out = checked_image(np.arange(6, dtype=np.uint16).reshape(2, 3), "frame", Bad)
    assert out.dtype == np.float64 and out.shape == (2, 3) and out[1, 2] == 5.0
    for image, message in ((np.ones((2, 2), bool), "frame: must be numeric, got dtype bool"),
                           (np.ones((2, 2, 3)), r"frame: expected shape \(H, W\), got \(2, 2, 3\)"),
                           (np.array([[1.0, np.nan]]), "frame: contains NaN or infinite values"),
                           (np.array([["a"]]), "frame: must be numeric")):
        with pytest.raises(Bad, match=message):
            checked_image(image, "frame", Bad)


@pytest.mark.parametrize("size", [1, 3, 5])
def test_the_median_of_a_batch_is_scipy_s_of_each_image(size):
    from scipy import ndimage

    x, _ = _batch(7)
    got = prepare.median_filter(torch.from_numpy(x), size).numpy()
    for i in range(len(x)):
        ref = ndimage.median_filter(x[i], size=size, mode="nearest")
        np.testing.assert_array_equal(got[i], ref)  # the median of an odd count is one of the values
        np.testing.assert_array_equal(prepare.median_filter(x[i], size), ref)


def test_log_correction_of_a_batch_is_each_image_s():
    rng = np.random.default_rng(8)
    L = rng.uniform(0.0, 6.0, (4, 12, 10))
    intensity = rng.uniform(500.0, 4000.0, (4, 1, 1)) * np.exp(-L)
    intensity[0, 0, 0] = 0.0  # below the floor: clipped to it
    t = torch.from_numpy(intensity)
    i0 = prepare.i0_percentile(t, None, 99.5)
    out = prepare.log_correct(t, i0, 1e-6).numpy()
    for k in range(4):
        ref_i0 = prepare.i0_percentile(intensity[k], None, 99.5)
        assert float(i0[k]) == ref_i0  # numpy's percentile, computed as numpy does
        np.testing.assert_allclose(out[k], prepare.log_correct(intensity[k], ref_i0, 1e-6), rtol=0, atol=1e-14)
    assert out[0, 0, 0] == pytest.approx(-np.log(1e-6))
