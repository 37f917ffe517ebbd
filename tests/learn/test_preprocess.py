"""Tests of learn.preprocess on images with known answers (ramps, deltas, steps, closed forms)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from learn.preprocess import (
    Compose,
    Gaussian,
    HistogramMatch,
    LearnPreprocessError,
    LocalContrast,
    LogCorrect,
    Median,
    Normalize,
    RandomConvolution,
    Sobel,
    build,
)


def _ramp(h=20, w=24, a=0.7, b=-1.3, dtype=torch.float64):
    rows = torch.arange(h, dtype=dtype)[:, None]
    cols = torch.arange(w, dtype=dtype)[None, :]
    return (a * cols + b * rows + 5.0)[None, None]


def test_sobel_of_ramp_is_its_slope_away_from_border():
    # I = a col + b row: the /8-normalised Sobel gives exactly a and b in the interior
    # (exact in float64 up to rounding: 1e-12), and |(a, b)| as magnitude.
    a, b = 0.7, -1.3
    x = _ramp(a=a, b=b)
    g = Sobel(mode="xy")(x)
    assert g.shape == (1, 2, 20, 24)
    inner = (slice(None), slice(None), slice(1, -1), slice(1, -1))
    torch.testing.assert_close(g[:, :1][inner], torch.full_like(g[:, :1][inner], a), rtol=0, atol=1e-12)
    torch.testing.assert_close(g[:, 1:][inner], torch.full_like(g[:, 1:][inner], b), rtol=0, atol=1e-12)
    # Pure column ramp: zero in the orthogonal (row) direction everywhere, replicate padding.
    gc = Sobel(mode="xy")(_ramp(a=2.0, b=0.0))
    assert float(gc[:, 1].abs().max()) < 1e-12
    m = Sobel()(x)
    assert m.shape == (1, 1, 20, 24)
    torch.testing.assert_close(m[inner], torch.full_like(m[inner], math.hypot(a, b)), rtol=0, atol=1e-12)


def test_gaussian_of_delta_is_sampled_kernel_and_preserves_sum_and_constant():
    sigma = 1.5
    x = torch.zeros(1, 1, 31, 31, dtype=torch.float64)
    x[0, 0, 15, 15] = 1.0
    y = Gaussian(sigma)(x)
    r = math.ceil(3 * sigma)
    k = torch.arange(-r, r + 1, dtype=torch.float64)
    g1 = torch.exp(-k**2 / (2 * sigma**2))
    g1 = g1 / g1.sum()
    expected = torch.zeros(31, 31, dtype=torch.float64)
    expected[15 - r:15 + r + 1, 15 - r:15 + r + 1] = torch.outer(g1, g1)
    torch.testing.assert_close(y[0, 0], expected, rtol=0, atol=1e-6)
    # Sum preserved (content further than r from the border), float32, 1e-5.
    rng = torch.Generator().manual_seed(0)
    img = torch.zeros(2, 1, 40, 40)
    img[:, :, 10:30, 10:30] = torch.rand(2, 1, 20, 20, generator=rng)
    torch.testing.assert_close(Gaussian(sigma)(img).sum((1, 2, 3)), img.sum((1, 2, 3)), rtol=1e-5, atol=0)
    c = torch.full((1, 1, 12, 9), 3.25)
    torch.testing.assert_close(Gaussian(2.0)(c), c, rtol=1e-6, atol=0)
    assert torch.equal(Gaussian(0.0)(img), img)


def test_median_removes_salt_and_keeps_step_edge():
    x = torch.zeros(1, 1, 16, 16)
    x[..., :, 8:] = 1.0  # vertical step edge
    noisy = x.clone()
    for r, c in [(3, 2), (10, 5), (12, 12), (5, 13)]:
        noisy[0, 0, r, c] = 50.0 if x[0, 0, r, c] == 0 else -50.0  # isolated outliers
    torch.testing.assert_close(Median(3)(noisy), x, rtol=0, atol=0)
    torch.testing.assert_close(Median(5)(x), x, rtol=0, atol=0)


def test_normalize_minmax_and_zscore():
    rng = torch.Generator().manual_seed(1)
    x = torch.rand(3, 1, 8, 10, generator=rng, dtype=torch.float64) * torch.tensor([1.0, 10.0, 100.0],
                                                                                    dtype=torch.float64)[:, None, None, None]
    y = Normalize()(x)
    torch.testing.assert_close(y.flatten(1).amin(1), -torch.ones(3, dtype=torch.float64), rtol=0, atol=1e-15)
    torch.testing.assert_close(y.flatten(1).amax(1), torch.ones(3, dtype=torch.float64), rtol=0, atol=1e-15)
    # Linear: the mid-range value maps to 0.
    lo, hi = x.flatten(1).amin(1), x.flatten(1).amax(1)
    torch.testing.assert_close(y, 2 * (x - lo[:, None, None, None]) / (hi - lo)[:, None, None, None] - 1)
    z = Normalize("zscore")(x)
    torch.testing.assert_close(z.flatten(1).mean(1), torch.zeros(3, dtype=torch.float64), rtol=0, atol=1e-12)
    torch.testing.assert_close(z.flatten(1).std(1, unbiased=False), torch.ones(3, dtype=torch.float64))
    assert torch.equal(Normalize()(torch.full((1, 1, 4, 4), 7.0)), torch.zeros(1, 1, 4, 4))


def test_log_correct_recovers_line_integral():
    rng = torch.Generator().manual_seed(2)
    L = torch.rand(2, 1, 20, 20, generator=rng, dtype=torch.float64) * 4.0
    L[:, :, :4, :] = 0.0  # 20 % of pixels unattenuated: the 99.5th percentile is exactly I0
    I0 = torch.tensor([1000.0, 3.5], dtype=torch.float64)[:, None, None, None]
    out = LogCorrect()(I0 * torch.exp(-L))
    torch.testing.assert_close(out, L, rtol=0, atol=1e-12)
    assert torch.equal(LogCorrect(input_kind="line_integral")(L), L)
    with pytest.raises(LearnPreprocessError, match="positive"):
        LogCorrect()(-torch.ones(1, 1, 4, 4))


def test_histogram_match_inverts_monotone_transform():
    rng = np.random.default_rng(3)
    ref = rng.normal(size=(32, 32)).astype(np.float64)
    img = torch.from_numpy(np.exp(2.0 * ref) + 3.0)[None, None]  # strictly increasing in ref
    out = HistogramMatch(ref)(img)
    torch.testing.assert_close(out[0, 0], torch.from_numpy(ref), rtol=0, atol=1e-12)
    # float32 input: exact up to float32 quantisation of the output (1e-5).
    out32 = HistogramMatch(torch.from_numpy(ref))(img.float())
    assert out32.dtype == torch.float32
    torch.testing.assert_close(out32[0, 0].double(), torch.from_numpy(ref), rtol=0, atol=1e-5)
    # Different pixel count: quantiles map monotonically onto the reference range.
    small = torch.linspace(0, 1, 16).reshape(1, 1, 4, 4)
    o = HistogramMatch(ref)(small).flatten()
    assert float(o[0]) == pytest.approx(ref.min()) and float(o[-1]) == pytest.approx(ref.max())
    assert bool((o[1:] >= o[:-1]).all())


def test_random_convolution_deterministic_shape_and_identity():
    rng = torch.Generator().manual_seed(4)
    x = torch.rand(3, 1, 16, 16, generator=rng)
    rc = RandomConvolution(kernel_sizes=(3, 5), p=1.0)
    y1 = rc(x, generator=torch.Generator().manual_seed(7))
    y2 = rc(x, generator=torch.Generator().manual_seed(7))
    assert y1.shape == x.shape and torch.equal(y1, y2)
    assert not torch.allclose(y1, x)
    y3 = rc(x, generator=torch.Generator().manual_seed(8))
    assert not torch.equal(y1, y3)
    # Re-normalised to each input image's [min, max].
    torch.testing.assert_close(y1.flatten(1).amin(1), x.flatten(1).amin(1))
    torch.testing.assert_close(y1.flatten(1).amax(1), x.flatten(1).amax(1))
    # Seeded module: two fresh modules with the same seed give the same sequence.
    a, b = RandomConvolution(p=1.0, seed=11), RandomConvolution(p=1.0, seed=11)
    assert torch.equal(a(x), b(x)) and torch.equal(a(x), b(x))
    assert torch.equal(RandomConvolution(p=0.0)(x), x)
    assert torch.equal(RandomConvolution(p=1.0).eval()(x), x)
    # Kernel size 1: a scalar multiple, re-normalised back to the input (or its mirror).
    y = RandomConvolution(kernel_sizes=(1,), p=1.0)(x, generator=torch.Generator().manual_seed(0))
    lo, hi = x.flatten(1).amin(1)[:, None, None, None], x.flatten(1).amax(1)[:, None, None, None]
    assert torch.allclose(y, x, atol=1e-5) or torch.allclose(y, lo + hi - x, atol=1e-5)


def test_compose_record_json_and_build_round_trip():
    ref = np.arange(16.0).reshape(4, 4)
    pipe = build(["log_correct", {"name": "gaussian", "sigma_px": 1.0}, "median",
                  {"name": "histogram_match", "reference": ref}, {"name": "normalize", "mode": "zscore"},
                  RandomConvolution(seed=3)])
    rec = pipe.record()
    text = json.dumps(rec)
    assert [r["name"] for r in json.loads(text)] == [
        "log_correct", "gaussian", "median", "histogram_match", "normalize", "random_convolution"]
    assert rec[1] == {"name": "gaussian", "sigma_px": 1.0}
    # Rebuilding from the records (all but histogram_match, whose record is a summary) agrees.
    rebuilt = build([r for r in rec if r["name"] not in ("histogram_match",)])
    assert rebuilt.record() == [r for r in rec if r["name"] != "histogram_match"]
    x = torch.rand(2, 1, 12, 12) + 0.5
    manual = Normalize("zscore")(Median(3)(Gaussian(1.0)(LogCorrect()(x))))
    torch.testing.assert_close(Compose([LogCorrect(), Gaussian(1.0), Median(3), Normalize("zscore")])(x), manual)


def test_errors_unknown_names_and_wrong_shapes():
    with pytest.raises(LearnPreprocessError, match="valid: .*gaussian"):
        build(["gausian"])
    with pytest.raises(LearnPreprocessError, match="bad parameters"):
        build([{"name": "median", "radius": 2}])
    with pytest.raises(LearnPreprocessError, match="reference"):
        build(["histogram_match"])
    with pytest.raises(LearnPreprocessError, match=r"\(B, 1, H, W\)"):
        Sobel()(torch.zeros(8, 8))
    with pytest.raises(LearnPreprocessError, match=r"\(B, 1, H, W\)"):
        build(["normalize"])(torch.zeros(8, 8))
    with pytest.raises(LearnPreprocessError, match="floating"):
        Median()(torch.zeros(1, 1, 4, 4, dtype=torch.int64))
    with pytest.raises(LearnPreprocessError, match="size"):
        Median(4)
    with pytest.raises(LearnPreprocessError, match="sigma_px"):
        Gaussian(-1.0)
    with pytest.raises(LearnPreprocessError, match="kernel_sizes"):
        RandomConvolution(kernel_sizes=(2,))


def test_local_contrast_removes_a_smooth_veil_and_a_gain_and_keeps_edges():
    """A step edge under a smooth additive veil (scatter-like) and a display gain: after local
    contrast normalisation the image equals that of the bare edge (away from the border, where the
    veil is locally linear to within ~1e-3 of the edge height over the window), and is invariant to
    a x + b exactly up to the eps term (which scales with a too)."""
    h = w = 64
    rows = torch.arange(h, dtype=torch.float64)[:, None].expand(h, w)
    cols = torch.arange(w, dtype=torch.float64)[None, :].expand(h, w)
    edge = (cols >= 32).to(torch.float64)
    veil = 0.3 * torch.exp(-((rows - 20) ** 2 + (cols - 40) ** 2) / (2 * 60.0 ** 2))
    lcn = LocalContrast(sigma_px=3.0, eps_rel=0.05)
    bare = lcn(edge[None, None])
    veiled = lcn((2.5 * (edge + veil) + 7.0)[None, None])
    inner = (slice(None), slice(None), slice(12, -12), slice(12, -12))
    torch.testing.assert_close(veiled[inner], bare[inner], atol=0.05, rtol=0)
    # the edge survives: a strong positive / negative pair straddles column 32; flat far away: 0
    assert bare[0, 0, 32, 32] > 0.5 and bare[0, 0, 32, 31] < -0.5
    assert bare[0, 0, 32, 5].abs() < 1e-6 and bare[0, 0, 32, 60].abs() < 1e-6
    # exact affine invariance (eps is relative to the global std)
    x = torch.rand(2, 1, 32, 32, dtype=torch.float64)
    torch.testing.assert_close(lcn(3.0 * x - 4.0), lcn(x), atol=1e-9, rtol=0)
    assert build([{"name": "local_contrast", "sigma_px": 3.0, "eps_rel": 0.05}]).record() == [lcn.to_dict()]
    with pytest.raises(LearnPreprocessError, match="sigma_px"):
        LocalContrast(sigma_px=0.0)
