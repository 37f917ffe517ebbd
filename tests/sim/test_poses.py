"""Pose distributions: ranges, uniformity, truncated normals, fixed values, validation, histogram."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from sim.campaign.poses import (
    ORIGINAL_PROTOCOL,
    PARAM_NAMES,
    PARAM_UNITS,
    ParamDistribution,
    PoseDistribution,
    PoseDistributionError,
    pose_histogram,
)

N = 20000


def rng(seed: int = 0) -> np.random.Generator:
    return np.random.default_rng(seed)


def test_original_protocol_is_the_published_one():
    expected = np.array([[-40, 40], [-20, 20], [-20, 20], [-75, 75], [-75, 75], [-75, 75]], float)
    np.testing.assert_array_equal(ORIGINAL_PROTOCOL.bounds(), expected)
    assert PARAM_NAMES == ("phi", "theta", "psi", "tx", "ty", "tz")
    assert PARAM_UNITS == ("deg", "deg", "deg", "mm", "mm", "mm")


def test_original_protocol_samples_stay_in_range_and_are_uniform():
    params = ORIGINAL_PROTOCOL.sample(rng(1), N)
    assert params.shape == (N, 6) and params.dtype == np.float64
    bounds = ORIGINAL_PROTOCOL.bounds()
    for k, name in enumerate(PARAM_NAMES):
        lo, hi = bounds[k]
        col = params[:, k]
        assert col.min() >= lo and col.max() < hi, name
        # 20 equal bins, expected N/20 each: a wrong range or a non-uniform map would be rejected
        counts, _ = np.histogram(col, bins=20, range=(lo, hi))
        assert counts.sum() == N
        p = stats.chisquare(counts).pvalue
        assert p > 1e-3, f"{name}: chi-square rejects uniformity (p = {p:.2e})"
        # the draws fill the range: the extremes lie within 0.1% of the range of the ends
        # (probability of failing for a correct sampler: 2 * 0.999^20000 ~ 4e-9)
        assert col.min() < lo + 1e-3 * (hi - lo) and col.max() > hi - 1e-3 * (hi - lo), name


def test_parameters_are_independent():
    # independent uniforms: sample correlation ~ N(0, 1/N); 5 sigma = 0.035
    params = ORIGINAL_PROTOCOL.sample(rng(2), N)
    corr = np.corrcoef(params.T)
    off = corr[~np.eye(6, dtype=bool)]
    assert np.abs(off).max() < 5 / math.sqrt(N)


def test_sampling_is_deterministic_and_prefix_stable():
    a = ORIGINAL_PROTOCOL.sample(rng(5), 100)
    b = ORIGINAL_PROTOCOL.sample(rng(5), 100)
    np.testing.assert_array_equal(a, b)
    # the first m poses do not depend on how many are drawn
    np.testing.assert_array_equal(ORIGINAL_PROTOCOL.sample(rng(5), 37), a[:37])
    assert not np.array_equal(ORIGINAL_PROTOCOL.sample(rng(6), 100), a)


def test_changing_one_parameter_leaves_the_others_unchanged():
    other = PoseDistribution.from_dict({"tx": {"dist": "fixed", "value": 3.0}})
    a = ORIGINAL_PROTOCOL.sample(rng(3), 50)
    b = other.sample(rng(3), 50)
    keep = [0, 1, 2, 4, 5]
    np.testing.assert_array_equal(a[:, keep], b[:, keep])
    assert np.all(b[:, 3] == 3.0)


def test_normal_with_wide_clip_has_the_normal_mean_and_std():
    d = ParamDistribution.from_dict({"dist": "normal", "mean": 5.0, "std": 10.0, "clip": [-95.0, 105.0]})
    x = d.sample(rng(7), N)
    assert x.min() >= -95.0 and x.max() <= 105.0
    # clip at +-10 std: truncation changes mean/std by < 1e-20; sampling error of the mean is
    # std/sqrt(N) = 0.07, of the std about std/sqrt(2N) = 0.05; allow 5 sigma
    assert abs(x.mean() - 5.0) < 5 * 10.0 / math.sqrt(N)
    assert abs(x.std() - 10.0) < 5 * 10.0 / math.sqrt(2 * N)
    # and the shape is normal: Kolmogorov-Smirnov against N(5, 10)
    assert stats.kstest(x, stats.norm(5.0, 10.0).cdf).pvalue > 1e-3


@pytest.mark.parametrize("clip", [(-1.0, 2.0), (4.0, 7.0), (-9.0, -6.5)])
def test_narrow_clip_matches_the_truncated_normal(clip):
    """Against scipy's truncnorm (independent implementation), including a far tail (4..7 std)."""
    mean, std = 1.0, 1.0 if clip != (-9.0, -6.5) else 1.5
    d = ParamDistribution("normal", mean=mean, std=std, clip=clip)
    x = d.sample(rng(11), N)
    assert x.min() >= clip[0] and x.max() <= clip[1]
    a, b = (clip[0] - mean) / std, (clip[1] - mean) / std
    truth = stats.truncnorm(a, b, loc=mean, scale=std)
    assert abs(x.mean() - truth.mean()) < 5 * truth.std() / math.sqrt(N)
    assert stats.kstest(x, truth.cdf).pvalue > 1e-3


def test_unclipped_normal_support_is_infinite_and_samples_are_finite():
    d = ParamDistribution("normal", mean=2.0, std=3.0)
    assert d.support() == (-math.inf, math.inf)
    # extreme uniforms (0 and the largest double below 1) still map to finite values
    x = d.from_unit(np.array([0.0, 0.5, 1.0 - 2.0**-53]))
    assert np.all(np.isfinite(x)) and x[1] == pytest.approx(2.0, abs=1e-12)


def test_fixed_gives_the_constant():
    d = ParamDistribution.from_dict({"dist": "fixed", "value": -12.5}, "poses.tz")
    np.testing.assert_array_equal(d.sample(rng(0), 10), np.full(10, -12.5))
    assert d.support() == (-12.5, -12.5)


def test_to_dict_round_trip():
    for d in [ParamDistribution("uniform", low=-3, high=4),
              ParamDistribution("normal", mean=0.0, std=2.0, clip=(-1.0, 3.0)),
              ParamDistribution("normal", mean=0.0, std=2.0),
              ParamDistribution("fixed", value=7)]:
        assert ParamDistribution.from_dict(d.to_dict()) == d
    assert PoseDistribution.from_dict(ORIGINAL_PROTOCOL.to_dict()) == ORIGINAL_PROTOCOL


@pytest.mark.parametrize("table, match", [
    ({"dist": "gaussian", "mean": 0, "std": 1}, r"poses\.phi\.dist.*uniform, normal, fixed"),
    ({"dist": "uniform", "low": 5.0, "high": 5.0}, r"poses\.phi.*low < high"),
    ({"dist": "uniform", "low": 6.0, "high": 5.0}, r"poses\.phi.*low < high"),
    ({"dist": "normal", "mean": 0.0, "std": -1.0}, r"poses\.phi\.std.*> 0"),
    ({"dist": "normal", "mean": 0.0, "std": 1.0, "clip": [2.0, 1.0]}, r"poses\.phi\.clip.*lo < hi"),
    ({"dist": "normal", "mean": 0.0, "std": 1.0, "clip": [1.0]}, r"poses\.phi\.clip.*\[lo, hi\]"),
    ({"dist": "normal", "mean": 0.0, "std": 1.0, "clip": [50.0, 60.0]}, r"poses\.phi\.clip.*too far"),
    ({"dist": "uniform", "low": -1.0, "hi": 1.0}, r"poses\.phi\.hi.*allowed keys: dist, low, high.*'high'"),
    ({"dist": "uniform", "low": -1.0}, r"poses\.phi.*needs 'high'"),
    ({"dist": "fixed", "value": "1"}, r"poses\.phi\.value.*number"),
    ({"dist": "uniform", "low": -1.0, "high": math.inf}, r"poses\.phi\.high.*finite"),
    ({"low": -1.0, "high": 1.0}, r"poses\.phi.*missing 'dist'"),
])
def test_bad_distributions_name_the_key_and_what_is_allowed(table, match):
    with pytest.raises(PoseDistributionError, match=match):
        ParamDistribution.from_dict(table, "poses.phi")


def test_unknown_pose_parameter_is_rejected_with_a_suggestion():
    with pytest.raises(PoseDistributionError, match=r"poses\.pis.*phi, theta, psi, tx, ty, tz.*'psi'"):
        PoseDistribution.from_dict({"pis": {"dist": "fixed", "value": 0.0}})


def test_histogram_png_is_written(tmp_path):
    from PIL import Image

    params = ORIGINAL_PROTOCOL.sample(rng(0), 500)
    dist = PoseDistribution.from_dict({"tz": {"dist": "normal", "mean": 0.0, "std": 20.0},
                                       "ty": {"dist": "fixed", "value": 1.0}})
    path = tmp_path / "sub" / "poses.png"
    pose_histogram(params, dist, path)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with Image.open(path) as im:
        im.verify()
    with Image.open(path) as im:
        assert im.size == (1200, 650)
        # not blank: the bars and lines put many distinct colours on the canvas
        assert len(np.unique(np.asarray(im.convert("L")))) > 10
    assert [p.name for p in path.parent.iterdir()] == ["poses.png"]  # no temporary left behind
    with pytest.raises(PoseDistributionError, match=r"params.*\(N, 6\)"):
        pose_histogram(params[:, :5], dist, tmp_path / "bad.png")
    assert not (tmp_path / "bad.png").exists()
