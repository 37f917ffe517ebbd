"""Similarity metrics: closed forms (identity, affine invariance, -1 for inversion), independent
references (np.corrcoef globally and per window, scipy's Sobel), the alignment peak, mask and
batch independence, the pyramid, block means and the input errors.

Tolerances: the metrics compute in float64, so identities and invariances hold to ~1e-12; 1e-6
(the brief's figure) leaves a wide margin while still failing on any formula error, which moves
scores by >= 1e-3 on these 24-64 px random images.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from register.engines.metrics import (
    METRICS,
    MetricError,
    NoWindowError,
    local_gradient_ncc,
    local_gradients,
    local_patch_px,
    bind_metric,
    downsample,
    get_metric,
    gradient_ncc,
    multiscale,
    ncc,
    patch_gradient_ncc,
    patch_ncc,
    tone_free_gradient_ncc,
    tone_matched,
    tone_tolerant_gradient_ncc,
)

RNG_SEED = 1234
H, W = 48, 56

#: Every metric as f(fixed, moving, mask=None) with small patches (fast, fits the images).
ALL = {
    "ncc": lambda f, m, mask=None: ncc(f, m, mask),
    "gncc": lambda f, m, mask=None: gradient_ncc(f, m, mask),
    "tone_free_gncc": lambda f, m, mask=None: tone_free_gradient_ncc(f, m, mask),
    "tone_tolerant_gncc": lambda f, m, mask=None: tone_tolerant_gradient_ncc(f, m, mask),
    "patch_ncc": lambda f, m, mask=None: patch_ncc(f, m, patch=7, mask=mask),
    "patch_gncc": lambda f, m, mask=None: patch_gradient_ncc(f, m, patch=7, mask=mask),
    "ms_ncc": lambda f, m, mask=None: multiscale("ncc", f, m, levels=3, mask=mask),
    "ms_patch_gncc": lambda f, m, mask=None: multiscale("patch_gncc", f, m, levels=2, mask=mask, patch=5),
}


def smooth_image(rng: np.random.Generator, shape=(H, W), sigma: float = 3.0) -> np.ndarray:
    """Gaussian-blurred white noise (sigma in px), affine-scaled to a DRR-like range."""
    img = ndimage.gaussian_filter(rng.normal(size=shape), sigma, mode="wrap")
    return (100.0 + 40.0 * img / img.std()).astype(np.float32)


@pytest.fixture
def rng():
    return np.random.default_rng(RNG_SEED)


@pytest.fixture
def mask():
    """A disc with a rectangular hole: irregular, not convex, touching no image border."""
    yy, xx = np.mgrid[:H, :W]
    k = (yy - H / 2) ** 2 + (xx - W / 2) ** 2 < (0.42 * H) ** 2
    k[20:26, 10:30] = False
    return k


# --------------------------------------------------------------------- identities and invariance


@pytest.mark.parametrize("name", ALL)
def test_identical_images_score_one(name, rng, mask):
    f = smooth_image(rng)
    for k in (None, mask):
        np.testing.assert_allclose(ALL[name](f, f, mask=k), [1.0], atol=1e-6)


@pytest.mark.parametrize("name", ALL)
def test_invariant_to_affine_intensity_change(name, rng, mask):
    f = smooth_image(rng).astype(np.float64)  # transform in float64: float32 rounding is not the metric's
    m = smooth_image(rng).astype(np.float64)  # a different image: the score is far from 1
    for k in (None, mask):
        ref = ALL[name](f, m, mask=k)
        assert abs(ref[0]) < 0.9
        np.testing.assert_allclose(ALL[name](f, 3.5 * m - 700.0, mask=k), ref, atol=1e-6)
        np.testing.assert_allclose(ALL[name](0.02 * f + 5.0, m, mask=k), ref, atol=1e-6)
        # a large offset on a small scale: naive E[x^2] - E[x]^2 box variances would cancel
        np.testing.assert_allclose(ALL[name](f, 1e-3 * m + 1e5, mask=k), ref, atol=1e-6)


@pytest.mark.parametrize("name", ["ncc", "gncc", "patch_ncc", "patch_gncc"])
def test_negative_scale_gives_minus_one(name, rng):
    f = smooth_image(rng)
    np.testing.assert_allclose(ALL[name](f, -2.0 * f + 3.0), [-1.0], atol=1e-6)


def test_ncc_matches_corrcoef_over_masked_pixels(rng, mask):
    f = rng.normal(size=(H, W))
    m = 0.5 * f + rng.normal(size=(3, H, W))
    got = ncc(f, m, mask)
    want = [np.corrcoef(f[mask], mi[mask])[0, 1] for mi in m]
    np.testing.assert_allclose(got, want, atol=1e-12)
    got_all = ncc(f, m)
    np.testing.assert_allclose(got_all, [np.corrcoef(f.ravel(), mi.ravel())[0, 1] for mi in m], atol=1e-12)


def test_constant_images_give_zero_not_nan(rng):
    f = smooth_image(rng)
    const = np.full((H, W), 7.0)
    for fn in ALL.values():
        assert np.array_equal(fn(f, const), [0.0])
        assert np.array_equal(fn(const, f), [0.0])


# --------------------------------------------------------------------- the tone-free gradient NCC


def _reference_tone_matched(f, m, mask):
    """Loop reference: each distinct value of f (inside the mask, ascending) takes the mean of m's
    sorted values over the rank range its pixels occupy."""
    out = f.astype(np.float64).copy()
    values = f[mask]
    sm = np.sort(m[mask])
    start = 0
    for v in np.unique(values):
        count = int(np.sum(values == v))
        out[mask & (f == v)] = sm[start:start + count].mean()
        start += count
    return out


def test_tone_matched_gives_ties_the_mean_of_their_rank_range(rng, mask):
    f = np.round(smooth_image(rng) * 3.0)  # a few grey levels: large tie groups
    m = smooth_image(rng) + rng.normal(0, 0.1, (H, W))
    got = tone_matched(f, m, mask)[0]
    np.testing.assert_allclose(got, _reference_tone_matched(f, m, mask), atol=1e-12)
    assert np.array_equal(got[~mask], f[~mask])  # outside the mask: untouched


def test_tone_free_gncc_ignores_any_increasing_display_curve(rng, mask):
    """gamma 2.6, a linear display of exp(-x), a window that clips nothing: the score of the curved
    image equals that of the original (to 1e-9: the ranks are the same), where plain gradient NCC
    moves by more than 0.01."""
    d = smooth_image(rng)
    x = d + 0.3 * smooth_image(rng, sigma=1.5)  # the X-ray: the DRR plus what it does not explain
    x01 = (x - x.min()) / np.ptp(x)
    moving = np.stack([d, np.roll(d, 3, axis=0)])
    ref = tone_free_gradient_ncc(x01, moving, mask)
    for curve in (lambda v: v ** 2.6, lambda v: 1.0 - np.exp(-4.0 * v), lambda v: np.log1p(50.0 * v)):
        np.testing.assert_allclose(tone_free_gradient_ncc(curve(x01), moving, mask), ref, atol=1e-9)
        assert np.max(np.abs(gradient_ncc(curve(x01), moving, mask) - gradient_ncc(x01, moving, mask))) > 0.01
    assert ref[0] > ref[1]  # and it still tells the right pose from a shifted one


# --------------------------------------------------------------------- independent references


def _reference_patch_ncc(f, m, patch, mask=None, min_valid=0.5):
    """Explicit loop over every window: np.corrcoef of the window's masked pixels."""
    h, w = f.shape
    k = np.ones_like(f, bool) if mask is None else mask
    fvals = f[k]
    gstd = fvals.std()
    vals = []
    for i in range(h - patch + 1):
        for j in range(w - patch + 1):
            kw = k[i : i + patch, j : j + patch]
            if kw.sum() < min_valid * patch * patch:
                continue
            fw = f[i : i + patch, j : j + patch][kw]
            mw = m[i : i + patch, j : j + patch][kw]
            if fw.std() <= 1e-4 * gstd:
                continue
            vals.append(np.corrcoef(fw, mw)[0, 1])
    return np.mean(vals)


def test_patch_ncc_matches_windowed_corrcoef(rng):
    f = rng.normal(size=(18, 21))
    m = 0.6 * f + rng.normal(size=(18, 21))
    yy, xx = np.mgrid[:18, :21]
    k = (yy - 9) ** 2 + (xx - 8) ** 2 < 60  # many windows straddle the mask edge
    for patch in (3, 5):
        np.testing.assert_allclose(patch_ncc(f, m, patch=patch), [_reference_patch_ncc(f, m, patch)], atol=1e-6)
        for mv in (0.5, 0.6, 0.8, 5 / 9):  # 0.6 x 25 = 15 and 5/9 x 9 = 5 px: ties at the bound count
            np.testing.assert_allclose(patch_ncc(f, m, patch=patch, mask=k, min_valid=mv),
                                       [_reference_patch_ncc(f, m, patch, k, mv)], atol=1e-6)


def test_gradient_ncc_matches_scipy_sobel_interior(rng, mask):
    f = rng.normal(size=(H, W))
    m = 0.4 * f + rng.normal(size=(H, W))
    eroded = ndimage.binary_erosion(mask, np.ones((3, 3), bool))
    want = np.mean([np.corrcoef(ndimage.sobel(f, axis=a)[eroded], ndimage.sobel(m, axis=a)[eroded])[0, 1]
                    for a in (0, 1)])
    np.testing.assert_allclose(gradient_ncc(f, m, mask), [want], atol=1e-12)
    inner = np.zeros((H, W), bool)
    inner[1:-1, 1:-1] = True  # no mask: the image's one-pixel border is left out
    want = np.mean([np.corrcoef(ndimage.sobel(f, axis=a)[inner], ndimage.sobel(m, axis=a)[inner])[0, 1]
                    for a in (0, 1)])
    np.testing.assert_allclose(gradient_ncc(f, m), [want], atol=1e-12)


def test_patch_gradient_ncc_is_patch_ncc_of_sobel_images(rng):
    f = rng.normal(size=(20, 24))
    m = 0.5 * f + rng.normal(size=(20, 24))
    want = np.mean([_reference_patch_ncc(ndimage.sobel(f, axis=a)[1:-1, 1:-1],
                                         ndimage.sobel(m, axis=a)[1:-1, 1:-1], 5) for a in (0, 1)])
    np.testing.assert_allclose(patch_gradient_ncc(f, m, patch=5), [want], atol=1e-6)


# --------------------------------------------------------------------- alignment, mask, batch


@pytest.mark.parametrize("name", ALL)
def test_maximum_at_alignment_and_monotone(name, rng):
    """Shifts of a smooth image (sigma 3 px) along x: the score peaks at 0 and falls for 0..3 px.

    np.roll wraps around, so every shift has the same content. The decrease must exceed 1e-4
    per pixel (rounding is ~1e-12; the true drop per pixel is >= 0.01 for sigma = 3 px), so a
    flat or noisy metric fails.
    """
    f = smooth_image(rng, (64, 64))
    shifts = np.arange(-5, 6)
    batch = np.stack([np.roll(f, s, axis=1) for s in shifts])
    scores = ALL[name](f, batch)
    zero = scores[shifts == 0][0]
    np.testing.assert_allclose(zero, 1.0, atol=1e-6)
    assert np.all(scores[shifts != 0] < zero - 1e-4)
    pos = scores[(shifts >= 0) & (shifts <= 3)]
    neg = scores[(shifts <= 0) & (shifts >= -3)][::-1]
    assert np.all(np.diff(pos) < -1e-4), pos
    assert np.all(np.diff(neg) < -1e-4), neg


@pytest.mark.parametrize("name", ALL)
def test_pixels_outside_mask_do_not_matter(name, rng, mask):
    f = smooth_image(rng)
    m = np.stack([smooth_image(rng), np.roll(f, 2, axis=0)])
    ref = ALL[name](f, m, mask=mask)
    f2, m2 = f.copy(), m.copy()
    f2[~mask] = rng.uniform(-1e4, 1e4, size=(~mask).sum())
    m2[:, ~mask] = rng.uniform(-1e4, 1e4, size=(2, (~mask).sum()))
    np.testing.assert_allclose(ALL[name](f2, m2, mask=mask), ref, atol=1e-9)
    # and the mask does change the score (so the test above is not vacuous)
    assert not np.allclose(ALL[name](f2, m2), ref, atol=1e-3)


@pytest.mark.parametrize("name", ALL)
def test_batch_equals_per_image(name, rng, mask):
    f = smooth_image(rng)
    m = np.stack([smooth_image(rng), np.roll(f, 1, axis=1), 2 * f + 1, np.flipud(f)])
    for k in (None, mask):
        batch = ALL[name](f, m, mask=k)
        assert batch.shape == (4,)
        single = np.concatenate([ALL[name](f, mi, mask=k) for mi in m])
        np.testing.assert_allclose(batch, single, atol=1e-12)


def test_float32_and_float64_agree(rng):
    f = smooth_image(rng)
    m = smooth_image(rng)
    for fn in ALL.values():
        np.testing.assert_allclose(fn(f, m), fn(f.astype(np.float64), m.astype(np.float64)), atol=1e-12)


# --------------------------------------------------------------------- registry, pyramid, downsample


def test_registry_names_and_lookup(rng):
    assert set(METRICS) == {"ncc", "gncc", "tone_free_gncc", "tone_tolerant_gncc", "patch_ncc", "patch_gncc",
                            "local_gncc"}
    f, m = smooth_image(rng), smooth_image(rng)
    np.testing.assert_allclose(get_metric("ncc")(f, m), ncc(f, m), atol=0)
    np.testing.assert_allclose(get_metric("gncc")(f, m), gradient_ncc(f, m), atol=0)
    np.testing.assert_allclose(get_metric("tone_free_gncc")(f, m), tone_free_gradient_ncc(f, m), atol=0)
    np.testing.assert_allclose(get_metric("tone_tolerant_gncc")(f, m),
                               0.5 * (gradient_ncc(f, m) + tone_free_gradient_ncc(f, m)), atol=1e-15)
    np.testing.assert_allclose(get_metric("patch_ncc")(f, m, patch=5), patch_ncc(f, m, patch=5), atol=0)
    np.testing.assert_allclose(get_metric("patch_gncc")(f, m, patch=5), patch_gradient_ncc(f, m, patch=5), atol=0)
    np.testing.assert_allclose(get_metric("local_gncc")(f, m),
                               patch_gradient_ncc(f, m, patch=local_patch_px(f.shape)), atol=0)
    with pytest.raises(MetricError, match="valid names: gncc, local_gncc, ncc, patch_gncc, patch_ncc, tone_free_gncc, tone_tolerant_gncc"):
        get_metric("mutual_information")


def test_multiscale_is_mean_over_pyramid(rng):
    f = rng.normal(size=(32, 40))
    m = rng.normal(size=(32, 40))
    levels_f, levels_m = [f], [m]
    for _ in range(2):  # independent pyramid: Gaussian sigma 1 on each image, every second pixel
        levels_f.append(ndimage.gaussian_filter(levels_f[-1], 1.0, mode="nearest")[::2, ::2])
        levels_m.append(ndimage.gaussian_filter(levels_m[-1], 1.0, mode="nearest")[::2, ::2])
    want = np.mean([np.corrcoef(a.ravel(), b.ravel())[0, 1] for a, b in zip(levels_f, levels_m)])
    np.testing.assert_allclose(multiscale("ncc", f, m, levels=3), [want], atol=1e-12)
    np.testing.assert_allclose(multiscale(ncc, f, f, levels=3), [1.0], atol=1e-12)
    np.testing.assert_allclose(multiscale("ncc", f, m, levels=1), ncc(f, m), atol=0)


def test_multiscale_masked_level_matches_reference(rng):
    """Level 1 with a block-aligned mask: mask-normalised Gaussian, every second pixel, 2 x 2
    min-pooled mask (an independent restatement with scipy)."""
    f = rng.normal(size=(32, 40))
    m = rng.normal(size=(32, 40))
    k = np.zeros((32, 40), bool)
    k[6:27, 8:33] = True  # odd extents: the min-pooled mask is rows 3..12, columns 4..15
    w = k.astype(float)
    pooled = np.zeros((16, 20), bool)
    pooled[3:13, 4:16] = True

    def level1(img):  # G(w) is 0 far from the mask (kernel truncated at 4 sigma); those pixels are unused
        with np.errstate(invalid="ignore"):
            return (ndimage.gaussian_filter(img * w, 1.0, mode="nearest")
                    / ndimage.gaussian_filter(w, 1.0, mode="nearest"))[::2, ::2]

    want = 0.5 * (np.corrcoef(f[k], m[k])[0, 1] + np.corrcoef(level1(f)[pooled], level1(m)[pooled])[0, 1])
    np.testing.assert_allclose(multiscale("ncc", f, m, levels=2, mask=k), [want], atol=1e-12)
    stripes = np.zeros((32, 40), bool)
    stripes[:, ::2] = True  # no 2 x 2 block is fully inside: nothing survives min-pooling
    with pytest.raises(MetricError, match="min-pooling"):
        multiscale("ncc", f, m, levels=2, mask=stripes)


def test_downsample_block_mean():
    a = np.arange(6 * 7, dtype=np.float32).reshape(6, 7)  # a[i, j] = 7 i + j
    d = downsample(a, 2)  # the last column is cropped
    # block (i, j) holds 7 (2i + {0,1}) + 2j + {0,1}: mean 14 i + 3.5 + 2 j + 0.5
    want = np.array([[14 * i + 2 * j + 4.0 for j in range(3)] for i in range(3)], np.float32)
    assert d.dtype == np.float32 and d.shape == (3, 3)
    np.testing.assert_array_equal(d, want)
    batch = np.stack([a, 2 * a])
    np.testing.assert_array_equal(downsample(batch, 3), np.stack([downsample(a, 3), downsample(2 * a, 3)]))
    np.testing.assert_array_equal(downsample(a, 3), [[a[:3, :3].mean(), a[:3, 3:6].mean()],
                                                      [a[3:, :3].mean(), a[3:, 3:6].mean()]])
    np.testing.assert_array_equal(downsample(a, 1), a)
    with pytest.raises(MetricError, match="factor"):
        downsample(a, 0)
    with pytest.raises(MetricError, match="smaller than factor"):
        downsample(a, 8)


# --------------------------------------------------------------------- errors


@pytest.mark.parametrize("name", ALL)
def test_input_errors(name, rng, mask):
    fn = ALL[name]
    f = smooth_image(rng)
    with pytest.raises(MetricError, match="does not match fixed"):
        fn(f, np.zeros((2, H, W + 1)))
    bad = f.copy()
    bad[3, 4] = np.nan
    with pytest.raises(MetricError, match="moving: contains 1 NaN"):
        fn(f, bad)
    with pytest.raises(MetricError, match="fixed: contains 1 NaN"):
        fn(bad, f)
    with pytest.raises(MetricError, match="mask: empty"):
        fn(f, f, mask=np.zeros((H, W), bool))
    with pytest.raises(MetricError, match="mask: shape"):
        fn(f, f, mask=np.ones((H, W + 1), bool))
    with pytest.raises(MetricError, match="mask: expected a bool"):
        fn(f, f, mask=np.ones((H, W)))


def test_patch_option_errors(rng):
    f = smooth_image(rng)
    with pytest.raises(MetricError, match="patch: expected an odd"):
        patch_ncc(f, f, patch=4)
    with pytest.raises(MetricError, match="do not fit"):
        patch_ncc(f, f, patch=H + 1)
    with pytest.raises(MetricError, match="min_valid"):
        patch_ncc(f, f, min_valid=0.0)
    thin = np.zeros((H, W), bool)
    thin[10, :] = True  # one row: no 7 x 7 window is half inside
    with pytest.raises(MetricError, match="no 7 x 7 window"):
        patch_ncc(f, f, patch=7, mask=thin)
    with pytest.raises(MetricError, match="empty after erosion"):
        gradient_ncc(f, f, mask=thin)
    with pytest.raises(MetricError, match="levels"):
        multiscale("ncc", f, f, levels=0)
    with pytest.raises(MetricError, match="valid names"):
        multiscale("nope", f, f)


def test_plain_equivalent_maps_the_display_tolerant_metrics_to_gradient_ncc():
    from register.engines.metrics import METRICS, plain_equivalent

    assert plain_equivalent("tone_tolerant_gncc") == "gncc" and plain_equivalent("tone_free_gncc") == "gncc"
    for name in METRICS:
        assert plain_equivalent(name) in METRICS
        if "tone" not in name:
            assert plain_equivalent(name) == name


# --------------------------------------------------------------------- a bound fixed image


@pytest.mark.parametrize("name", sorted(METRICS))
@pytest.mark.parametrize("levels", [None, 12])
def test_a_bound_metric_scores_as_the_metric_to_the_bit(name, rng, mask, levels):
    """bind_metric prepares the X-ray's side once: the same scores, bit for bit, for every metric
    (the patch metrics at their default options), with and without a mask, over several batches of
    one fixed image: a noisy one without ties, and one quantised to 12 grey levels, whose ties the
    rank match averages."""
    f = smooth_image(rng)
    if levels is not None:
        f = np.round((f - f.min()) / np.ptp(f) * (levels - 1))
    for k in (None, mask):
        score = bind_metric(name, f, k)
        for b in (1, 3):
            m = np.stack([smooth_image(rng) for _ in range(b)])
            np.testing.assert_array_equal(score(m), get_metric(name)(f, m, mask=k))
        np.testing.assert_array_equal(score(m[0]), get_metric(name)(f, m[0], mask=k))  # (H, W): a batch of one


def _with_nan(f):
    g = np.array(f, np.float64)
    g[3, 4] = np.nan
    return g


def test_a_bound_metric_checks_its_inputs(rng, mask):
    """The name, the fixed image and the mask when bound; each moving batch when scored."""
    f = smooth_image(rng)
    with pytest.raises(MetricError, match="unknown name"):
        bind_metric("gradient", f)
    with pytest.raises(MetricError, match="mask: empty"):
        bind_metric("gncc", f, np.zeros_like(mask))
    with pytest.raises(MetricError, match="fixed: contains 1 NaN"):
        bind_metric("tone_tolerant_gncc", _with_nan(f))
    score = bind_metric("tone_tolerant_gncc", f, mask)
    with pytest.raises(MetricError, match="does not match fixed"):
        score(f[:-1])
    with pytest.raises(MetricError, match="moving: contains 1 NaN"):
        score(_with_nan(f))


def test_the_modules_examples_run():
    import doctest

    import register.engines.metrics as metrics

    assert doctest.testmod(metrics).failed == 0


def test_the_local_similarity_scales_its_window_with_the_image_and_says_when_no_window_fits(rng):
    # the same anatomy at 64 and 128 px: 7 and 15 px windows, the same share of it
    assert (local_patch_px((64, 48)), local_patch_px((128, 96)), local_patch_px((3, 256, 200))) == (7, 15, 31)
    f, m = smooth_image(rng), smooth_image(rng)
    np.testing.assert_allclose(local_gradient_ncc(f, m), patch_gradient_ncc(f, m, patch=local_patch_px(f.shape)), atol=0)
    dot = np.zeros(f.shape, bool)
    dot[10:14, 10:14] = True  # a field smaller than one window
    with pytest.raises(NoWindowError, match="no .* window"):
        local_gradient_ncc(f, m, mask=dot)


def test_local_gradients_put_every_regions_edges_at_one_strength(rng):
    # a step of 100 (a body's outline) and texture of sd 1 (bones) side by side: their raw gradients
    # differ 100-fold, the locally normalized ones are alike; outside the mask they are 0, and a
    # batch is normalized image by image (each its own floor)
    img = smooth_image(rng, sigma=2.0).astype(np.float64) / 40.0
    img[:, W // 2:] += 100.0
    gx, gy = local_gradients(img, sigma_px=2.0)
    mag = np.hypot(gx, gy)
    edge = mag[:, W // 2 - 1:W // 2 + 1].mean()
    texture = mag[:, 4:W // 2 - 8].mean()
    raw = np.hypot(ndimage.sobel(img, axis=-1), ndimage.sobel(img, axis=-2))
    assert raw[:, W // 2 - 1:W // 2 + 1].mean() > 50 * raw[:, 4:W // 2 - 8].mean()
    assert 0.5 < edge / texture < 3.0
    mask = np.zeros(img.shape, bool)
    mask[:, : W // 2 - 4] = True
    mx, my = local_gradients(img, mask, sigma_px=2.0)
    assert not mx[~mask].any() and not my[~mask].any()
    batch = np.stack([img, 3.0 * img + 7.0])
    bx, _ = local_gradients(batch, sigma_px=2.0)
    np.testing.assert_allclose(bx[0], gx, atol=1e-12)
    np.testing.assert_allclose(bx[1], gx, atol=1e-9)  # affine-invariant: the scale divides out
    with pytest.raises(MetricError, match="sigma_px"):
        local_gradients(img, sigma_px=0.0)
